"""Models known before jobs start: the worker's offline check, its heartbeat, /readyz, refusal at submission
and failure at the start of the chain (SQLite, the in-process API and the real worker code)."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import pytest
from sqlalchemy import select

from test_service_api import client, dataset, make_scene, root  # noqa: F401 - the service fixtures
from voxe_core.constants import INCEPTION_FILE
from voxe_core.guidance.loading import (CLIP_FILES, CLIP_TOKENIZERS, DIFFUSERS_FILES, diffusers_model_present,
                                       download_command, model_file)
from voxe_core.tiny_eval import build_tiny_inception
from voxe_service.model_inventory import ROLES, check_models, unavailable_models

ABSENT = "nobody-here/absent-diffusion-model"
WHOLE_SD = (*DIFFUSERS_FILES, "unet/diffusion_pytorch_model.safetensors", "vae/diffusion_pytorch_model.safetensors",
            "text_encoder/model.safetensors")
"""The files of a whole diffusers-layout Stable Diffusion (SD 2's names) that the presence check looks for."""
WHOLE_CLIP = (*CLIP_FILES, *CLIP_TOKENIZERS[0], "model.safetensors")
"""The files of a whole CLIP model (the tiny one's) that the presence check looks for."""


@pytest.fixture
def hub_cache(tmp_path, monkeypatch):
    """An empty Hugging Face hub cache; ``cache(repo, *files)`` puts ``files`` in a snapshot of ``repo`` in it."""
    import huggingface_hub.constants

    folder = tmp_path / "hub"
    folder.mkdir()
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(folder))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")

    def cache(repo: str, *files: str) -> None:
        repo_dir = folder / f"models--{repo.replace('/', '--')}"
        (repo_dir / "refs").mkdir(parents=True, exist_ok=True)
        (repo_dir / "refs" / "main").write_text("0" * 40)
        snapshot = repo_dir / "snapshots" / ("0" * 40)
        snapshot.mkdir(parents=True, exist_ok=True)
        for name in files:
            (snapshot / name).parent.mkdir(parents=True, exist_ok=True)
            (snapshot / name).write_text("{}")

    return cache


def test_presence_is_one_small_file_in_a_folder_or_the_hub_cache(tmp_path, hub_cache):
    folder = tmp_path / "sd"
    folder.mkdir()
    assert model_file(str(folder), "model_index.json") is None
    (folder / "model_index.json").write_text("{}")
    assert model_file(str(folder), "model_index.json") is not None
    assert model_file(str(tmp_path / "missing"), "model_index.json") is None
    assert model_file("owner/cached-model", "model_index.json") is None
    hub_cache("owner/cached-model", "model_index.json")
    assert model_file("owner/cached-model", "model_index.json") is not None
    assert model_file("owner/cached-model", "config.json") is None
    assert model_file("not a valid id!", "model_index.json") is None


def test_a_diffusion_model_is_present_only_whole_in_a_folder_or_the_hub_cache(tmp_path, hub_cache):
    """model_index.json alone had counted: a download cut short (the UNet's weights never arrived) or a folder
    without vae/ was offered by the workers, and its jobs failed at the edit, after their reconstruction."""
    def folder(name: str, files) -> str:
        for file in files:
            (tmp_path / name / file).parent.mkdir(parents=True, exist_ok=True)
            (tmp_path / name / file).write_text("{}")
        return str(tmp_path / name)

    assert diffusers_model_present(folder("whole", WHOLE_SD))
    hub_cache("owner/whole", *WHOLE_SD)
    assert diffusers_model_present("owner/whole")
    bin_weights = [name.replace(".safetensors", ".bin") for name in WHOLE_SD]  # the older weights format
    assert diffusers_model_present(folder("bin", bin_weights))
    for i, lacking in enumerate(WHOLE_SD[1:]):  # model_index.json, which loading does not read, is not needed
        files = [name for name in WHOLE_SD if name != lacking]
        assert not diffusers_model_present(folder(f"lacks-{i}", files)), lacking
        hub_cache(f"owner/lacks-{i}", *files)
        assert not diffusers_model_present(f"owner/lacks-{i}"), lacking
    # In the cache a snapshot's file is a link to its blob: one whose blob is gone is not there either.
    hub_cache("owner/dangling", *WHOLE_SD)
    weights = tmp_path / "hub" / "models--owner--dangling" / "snapshots" / ("0" * 40) / WHOLE_SD[-1]
    weights.unlink()
    weights.symlink_to(tmp_path / "hub" / "models--owner--dangling" / "blobs" / "gone")
    assert not diffusers_model_present("owner/dangling")


def test_a_sharded_diffusion_component_is_present_only_with_every_shard_its_index_names(tmp_path):
    """Any one weights file had counted: a UNet sharded in two, its second shard not yet arrived, was offered by the
    workers, and its jobs failed loading it at the edit."""
    unet_weights = "unet/diffusion_pytorch_model.safetensors"
    shards = ["diffusion_pytorch_model-00001-of-00002.safetensors", "diffusion_pytorch_model-00002-of-00002.safetensors"]
    folder = tmp_path / "sharded"
    for name in [file for file in WHOLE_SD if file != unet_weights] + [f"unet/{shards[0]}"]:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text("{}")
    (folder / f"{unet_weights}.index.json").write_text(json.dumps({"metadata": {}, "weight_map": {
        "conv_in.weight": shards[0], "conv_out.weight": shards[1]}}))
    assert not diffusers_model_present(str(folder))
    (folder / "unet" / shards[1]).write_text("{}")
    assert diffusers_model_present(str(folder))


def test_a_clip_model_is_present_only_whole_in_a_folder_or_the_hub_cache(tmp_path, hub_cache, monkeypatch):
    """config.json alone had counted: a download cut short (the weights never arrived) was offered by the workers, and
    an evaluation sweep failed loading it only after all its edits had run."""
    from safetensors import safe_open

    from voxe_core.evaluate import ClipScorer
    from voxe_core.guidance import loading
    from voxe_core.guidance.loading import ModelNotAvailableError
    from voxe_core.tiny_eval import build_tiny_clip
    from voxe_service.model_inventory import model_present
    from voxe_service.settings import Settings

    clip, settings = ROLES["clip"], Settings(model_dir=str(tmp_path / "models"))
    whole = build_tiny_clip(tmp_path / "whole")
    assert model_present(clip, str(whole), settings)
    ClipScorer.from_pretrained(str(whole), device="cpu")  # what presence promises: it loads
    for lacking in WHOLE_CLIP:
        partial = shutil.copytree(whole, tmp_path / f"lacks-{lacking}")
        (partial / lacking).unlink()
        assert not model_present(clip, str(partial), settings), lacking
        with pytest.raises(ModelNotAvailableError):
            ClipScorer.from_pretrained(str(partial), device="cpu")
    (whole / "model.safetensors").rename(whole / "pytorch_model.bin")  # the older weights format
    assert model_present(clip, str(whole), settings)
    hub_cache("owner/whole-clip", *WHOLE_CLIP)
    assert model_present(clip, "owner/whole-clip", settings)
    for i, lacking in enumerate(WHOLE_CLIP):
        hub_cache(f"owner/clip-lacks-{i}", *(name for name in WHOLE_CLIP if name != lacking))
        assert not model_present(clip, f"owner/clip-lacks-{i}", settings), lacking
    tokenizer_json = [*CLIP_FILES, *CLIP_TOKENIZERS[1], "model.safetensors"]  # transformers 5's, and it reads it alone
    hub_cache("owner/clip-tokenizer-json", *tokenizer_json)
    assert model_present(clip, "owner/clip-tokenizer-json", settings)
    monkeypatch.setattr(loading, "_transformers_major", lambda: 4)  # whose CLIPTokenizer needs vocab.json, merges.txt
    assert not model_present(clip, "owner/clip-tokenizer-json", settings)
    monkeypatch.undo()
    # Sharded weights: the index arrives before its shards, and had counted alone
    sharded = shutil.copytree(tmp_path / "lacks-model.safetensors", tmp_path / "sharded")
    shard = shutil.copy(tmp_path / "lacks-config.json" / "model.safetensors",
                        sharded / "model-00001-of-00001.safetensors")
    with safe_open(shard, "pt") as weights:
        names = list(weights.keys())
    (sharded / "model.safetensors.index.json").write_text(json.dumps({"metadata": {}, "weight_map": {
        name: "model-00001-of-00001.safetensors" for name in names}}))
    assert model_present(clip, str(sharded), settings)
    ClipScorer.from_pretrained(str(sharded), device="cpu")
    Path(shard).unlink()
    assert not model_present(clip, str(sharded), settings)


def test_the_worker_inventory_counts_tiny_models_and_finds_the_missing(root, hub_cache, monkeypatch):
    from voxe_service.settings import Settings

    hub_cache("owner/clip", *WHOLE_CLIP)
    settings = Settings(sds_model="tiny", attention_model=ABSENT, clip_model="owner/clip", fid_model="")
    assert check_models(settings) == {
        "sds": {"model": "tiny", "present": True},
        "attention": {"model": ABSENT, "present": False},
        "clip": {"model": "owner/clip", "present": True},
        "fid": {"model": "", "present": False},  # no Inception file in VOXE_MODEL_DIR
    }
    (root / "models").mkdir(exist_ok=True)
    build_tiny_inception(root / "models" / "inception-2015-12-05.pt")
    assert check_models(settings)["fid"]["present"]


def test_an_fid_model_folder_is_present_when_it_holds_the_file_the_loader_reads(tmp_path):
    from voxe_service.model_inventory import model_present
    from voxe_service.settings import Settings

    settings = Settings(model_dir=str(tmp_path / "models"))
    folder = tmp_path / "inception"
    folder.mkdir()
    assert not model_present(ROLES["fid"], str(folder), settings)
    build_tiny_inception(folder / INCEPTION_FILE)
    assert model_present(ROLES["fid"], str(folder), settings)  # InceptionFeatures.load reads folder/INCEPTION_FILE
    assert model_present(ROLES["fid"], str(folder / INCEPTION_FILE), settings)


def test_an_fid_model_file_cut_short_is_not_present(tmp_path):
    """Any file had counted: a download cut short (curl -o writes under the final name) was offered by the workers,
    and an evaluation sweep failed loading it ("not a TorchScript Inception file") only after all its edits had run."""
    from voxe_core.evaluate import InceptionFeatures
    from voxe_core.guidance.loading import ModelNotAvailableError
    from voxe_service.model_inventory import model_present
    from voxe_service.settings import Settings

    whole = build_tiny_inception(tmp_path / "whole" / INCEPTION_FILE)
    cut = tmp_path / "cut" / INCEPTION_FILE
    cut.parent.mkdir()
    cut.write_bytes(whole.read_bytes()[:whole.stat().st_size // 2])
    settings = Settings(model_dir=str(cut.parent))
    assert not model_present(ROLES["fid"], "", settings)
    with pytest.raises(ModelNotAvailableError, match="is not a TorchScript Inception file"):
        InceptionFeatures.load(str(cut), device="cpu")
    assert model_present(ROLES["fid"], "", Settings(model_dir=str(whole.parent)))


def test_a_model_is_refused_only_when_every_worker_reporting_on_it_lacks_it():
    has = {"sds": {"model": "a/b", "present": True}}
    lacks = {"sds": {"model": "a/b", "present": False}}
    other = {"sds": {"model": "c/d", "present": True}}
    assert unavailable_models({"sds": "a/b"}, {"w1": has, "w2": lacks}) == []
    assert unavailable_models({"sds": "a/b"}, {"w1": other, "w2": None}) == []  # nobody checked a/b
    (message,) = unavailable_models({"sds": "a/b"}, {"w2": lacks, "w3": other})
    for part in ("sds model 'a/b'", "(w2)", "HF_HOME", "hf download a/b", API_SETTING.format("VOXE_SDS_MODEL"),
                 "the API's VOXE_SDS_MODEL may name another", "VOXE_SDS_MODEL=tiny"):
        assert part in message, message
    (fid,) = unavailable_models({"fid": ""}, {"w": {"fid": {"model": "", "present": False}}})
    assert "inception-2015-12-05.pt in the workers' VOXE_MODEL_DIR" in fid
    assert API_SETTING.format("VOXE_FID_MODEL") in fid


@pytest.mark.parametrize("role, model, folder", [("sds", "/models/sd", "/models/sd"),
                                                ("attention", "models/sd/v1-4", "models/sd/v1-4"),
                                                ("clip", "~/models/clip", str(Path("~/models/clip").expanduser()))])
def test_a_missing_model_folder_is_to_be_filled_not_downloaded(role, model, folder):
    """A folder no worker has had been advised `hf download /models/sd`, which no hub id is (the hub refuses it)."""
    (message,) = unavailable_models({role: model}, {"w": {role: {"model": model, "present": False}}})
    assert f"is not on any worker (w): put the whole model ({ROLES[role].marker}) in the folder {folder!r} on the " \
           "workers." in message, message
    assert "hf download" not in message and API_SETTING.format(ROLES[role].variable) in message


API_SETTING = "A job loads the model the API's {0} named when the job was submitted (a worker's own {0} only chooses"
"""Where the messages about a missing model say a job's model comes from: a job carries the API's setting at its
submission; the worker's own setting had been named as the one to change, which changed only its heartbeat."""


@pytest.mark.parametrize("stage, variable", [("edit", "VOXE_SDS_MODEL"), ("refine", "VOXE_ATTENTION_MODEL")])
def test_a_model_that_fails_to_load_is_blamed_on_the_apis_setting_at_submission(stage, variable):
    from types import SimpleNamespace

    from voxe_core.guidance.loading import ModelNotAvailableError
    from worker.tasks import _error_message

    text = _error_message(stage, ModelNotAvailableError("weights 'a/b' are not available"), SimpleNamespace())
    assert text.startswith(f"{stage}: weights 'a/b' are not available. {API_SETTING.format(variable)}"), text
    assert "The worker reads the model" not in text


def test_an_evaluation_model_that_fails_to_load_is_blamed_on_the_apis_setting(root, monkeypatch):
    from voxe_service.settings import get_settings
    from worker import evaluation

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(evaluation.EvaluationFailed) as failed:
        evaluation._scorer("clip", "voxe-test/no-such-clip", "cpu", get_settings())
    assert API_SETTING.format("VOXE_CLIP_MODEL") in str(failed.value)
    assert "The worker reads this model" not in str(failed.value)


def test_a_worker_keeps_one_evaluation_model_of_each_kind_loaded(root, monkeypatch):
    """Each (kind, model, device) had stayed loaded for the worker's life: evaluations with several CLIP and FID
    models kept every one. Now the last of each kind stays; one of another model or device replaces it, let go
    before the new one loads (two were never needed at once)."""
    import gc
    import weakref

    from voxe_core.evaluate import ClipScorer, InceptionFeatures
    from voxe_service.settings import get_settings
    from worker import evaluation

    class Model:
        def __init__(self, kind, name, device):
            self.kind, self.name, self.device = kind, name, device

    loads, alive = [], []

    def load(kind):
        def loader(path, device=None):
            alive.append(sum(ref() is not None for ref in refs))  # models of any kind still alive as this loads
            loads.append((kind, path, device))
            model = Model(kind, path, device)
            refs.append(weakref.ref(model))
            return model
        return staticmethod(loader)

    refs = []
    monkeypatch.setattr(evaluation, "_SCORERS", {})
    monkeypatch.setattr(ClipScorer, "from_pretrained", load("clip"))
    monkeypatch.setattr(InceptionFeatures, "load", load("fid"))
    settings = get_settings()
    clip_a = evaluation._scorer("clip", "clip-a", "cpu", settings)
    fid_a = evaluation._scorer("fid", "/models/fid-a.pt", "cpu", settings)
    assert evaluation._scorer("clip", "clip-a", "cpu", settings) is clip_a  # the same model: not loaded again
    assert evaluation._scorer("fid", "/models/fid-a.pt", "cpu", settings) is fid_a
    first = weakref.ref(clip_a)
    del clip_a
    clip_b = evaluation._scorer("clip", "clip-b", "cpu", settings)
    gc.collect()
    assert first() is None and alive[-1] == 1  # clip-a let go before clip-b loaded; fid-a kept
    assert evaluation._scorer("fid", "/models/fid-a.pt", "cpu", settings) is fid_a
    evaluation._scorer("clip", "clip-b", "meta", settings)  # another device is another model to hold
    assert loads == [("clip", "clip-a", "cpu"), ("fid", "/models/fid-a.pt", "cpu"), ("clip", "clip-b", "cpu"),
                     ("clip", "clip-b", "meta")]
    del clip_b
    gc.collect()
    assert sum(ref() is not None for ref in refs) == 2 and len(evaluation._SCORERS) == 2


def heartbeat_row(until=lambda beat: True) -> dict:
    """The worker's heartbeat row once written and ``until(row)`` holds (within 5 s)."""
    from voxe_service.db import session_scope
    from voxe_service.models import WorkerHeartbeat

    for _ in range(100):
        with session_scope() as session:
            row = session.scalars(select(WorkerHeartbeat)).first()
            beat = row and {"hostname": row.hostname, "models": row.models, "last_seen": row.last_seen}
        if beat and until(beat):
            return beat
        time.sleep(0.05)
    raise AssertionError(f"no heartbeat written, or none such: {beat}")


@pytest.fixture
def worker_heartbeat(monkeypatch):
    """The worker's start-up hook as Celery calls it (no sender), beating every 0.1 s until the test ends; its
    first heartbeat row, once its first scratch sweep removed the leftover folder of a job that no longer exists."""
    from voxe_service.settings import get_settings
    from worker import runtime, tasks

    monkeypatch.setattr(get_settings(), "worker_heartbeat_s", 0.1)
    leftover = runtime.scratch_dir("f" * 32, get_settings())  # of no job: the first sweep removes it
    tasks._start_heartbeat(sender=None)
    try:
        yield heartbeat_row(until=lambda beat: not leftover.exists())
    finally:
        tasks._heartbeat_stop.set()


def test_the_heartbeat_records_the_models_and_readyz_and_submission_use_them(root, client, dataset, hub_cache,
                                                                             worker_heartbeat, monkeypatch):
    from voxe_service.settings import get_settings

    monkeypatch.setattr(get_settings(), "sds_model", ABSENT)  # the worker's and the API's setting alike
    beat = heartbeat_row(until=lambda beat: beat["models"]["sds"]["model"] == ABSENT)
    assert beat["models"]["sds"] == {"model": ABSENT, "present": False}
    assert beat["models"]["attention"] == {"model": "tiny", "present": True}
    ready = client.get("/readyz").json()
    assert ready["checks"]["worker"]["workers"] == [beat["hostname"]]
    assert ready["model_availability"]["sds"] == {"model": ABSENT, "setting": "VOXE_SDS_MODEL", "workers_with": [],
                                                  "workers_without": [beat["hostname"]], "reported": True,
                                                  "workers_reporting_other": []}
    assert ready["model_availability"]["attention"]["workers_with"] == [beat["hostname"]]

    scene = make_scene(client, dataset, root)
    refused = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of gold"})
    assert refused.status_code == 409
    for part in (f"sds model '{ABSENT}'", beat["hostname"], API_SETTING.format("VOXE_SDS_MODEL"), "HF_HOME",
                 f"hf download {ABSENT}"):
        assert part in refused.json()["detail"], refused.json()["detail"]
    assert client.get("/v1/jobs").json()["total"] == 0  # nothing recorded

    # Downloaded while the worker runs: its next beat offers the model, with no restart (it had been checked
    # only when the worker started, so every job was refused until then).
    hub_cache(ABSENT, "model_index.json")  # a download under way: not offered yet
    assert not check_models(get_settings())["sds"]["present"]
    hub_cache(ABSENT, *WHOLE_SD)
    assert heartbeat_row(until=lambda beat: beat["models"]["sds"]["present"])["hostname"] == beat["hostname"]
    accepted = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of gold"})
    assert accepted.status_code == 201, accepted.text


def test_readyz_says_when_no_live_worker_reports_the_model_jobs_will_ask_for(root, client, monkeypatch):
    """Workers report on the models of their own settings; jobs load the API's. A worker set to others said nothing
    of the API's model, and /readyz showed that only as empty lists, as if no worker were up."""
    from voxe_service.db import session_scope
    from voxe_service.models import WorkerHeartbeat
    from voxe_service.settings import get_settings

    monkeypatch.setattr(get_settings(), "sds_model", ABSENT)  # the API's; the worker below is set to `tiny`
    tiny = {"model": "tiny", "present": True}
    with session_scope() as session:
        session.add(WorkerHeartbeat(hostname="w-tiny", pid=1, queues="gpu", device="cpu",
                                    models={"sds": tiny, "attention": tiny}))
    availability = client.get("/readyz").json()["model_availability"]
    assert availability["sds"] == {"model": ABSENT, "setting": "VOXE_SDS_MODEL", "workers_with": [],
                                   "workers_without": [], "reported": False, "workers_reporting_other": ["w-tiny"]}
    assert availability["attention"]["reported"] and availability["attention"]["workers_with"] == ["w-tiny"]
    assert availability["attention"]["workers_reporting_other"] == []
    assert not availability["clip"]["reported"] and availability["clip"]["workers_reporting_other"] == []


def test_a_model_check_that_fails_keeps_the_last_answer_and_the_heartbeat(root, client, worker_heartbeat, monkeypatch):
    """An unreadable models volume raises in the check: the worker must not look dead for it."""
    from worker import tasks

    def unreadable(settings):
        raise PermissionError("models volume unreadable")

    monkeypatch.setattr(tasks, "check_models", unreadable)
    later = heartbeat_row(until=lambda beat: beat["last_seen"] > worker_heartbeat["last_seen"])
    assert later["models"] == worker_heartbeat["models"]


def test_a_job_sent_before_any_worker_reported_fails_at_the_start_of_its_chain(root, client, dataset, hub_cache,
                                                                                monkeypatch):
    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction
    from voxe_service.settings import get_settings
    from worker import tasks

    monkeypatch.setattr(get_settings(), "attention_model", ABSENT)
    scene = make_scene(client, dataset, root)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic wearing a party hat",
                                        "mode": "local", "edit_words": ["party hat"]})
    assert job.status_code == 201, job.text  # no worker has said what it has: accepted, queued
    assert tasks.reconstruct_task.apply(args=(job.json()["id"],)).get()["state"] == "failed"
    failed = client.get(f"/v1/jobs/{job.json()['id']}").json()
    assert failed["state"] == "failed"
    assert failed["error"].startswith(f"reconstruct: not started: the attention model '{ABSENT}' is not on this worker")
    assert API_SETTING.format("VOXE_ATTENTION_MODEL") in failed["error"] and "HF_HOME" in failed["error"]
    with session_scope() as session:  # the reconstruction never ran
        rec = session.scalars(select(Reconstruction).where(Reconstruction.scene_id == scene["id"])).one()
        assert rec.grid_key is None and rec.iteration == 0 and rec.owner_job_id is None


def test_a_prompt_longer_than_its_models_tokenizer_reads_fails_at_the_start_of_its_chain(root, client, dataset):
    """The API's prompt check is a lower bound (a piece a token); BPE splits words the vocabulary lacks (the
    smoke-test model's tokenizer spells them letter by letter). Such a job had run its whole fit, then failed at
    the edit; the worker counts with the model's own tokenizer before the fit."""
    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction
    from worker import tasks

    scene = make_scene(client, dataset, root)
    prompt = "a mic wearing " + "zyxwv " * 14 + "sunglasses"  # 26 tokens at least, 82 as the tokenizer reads it
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": prompt})
    assert job.status_code == 201, job.text
    assert tasks.reconstruct_task.apply(args=(job.json()["id"],)).get()["state"] == "failed"
    error = client.get(f"/v1/jobs/{job.json()['id']}").json()["error"]
    assert error.startswith("reconstruct: not started: the prompt 'a render of a mic wearing zyxwv") and error.endswith(
        "tokens as the model's tokenizer reads it; its text encoder reads 77, its start and end tokens included: "
        "shorten it (the sds model 'tiny')")
    with session_scope() as session:  # the reconstruction never ran
        rec = session.scalars(select(Reconstruction).where(Reconstruction.scene_id == scene["id"])).one()
        assert rec.grid_key is None and rec.iteration == 0


def test_a_prompt_longer_than_the_attention_model_reads_fails_at_the_start_of_its_chain(root, client, dataset,
                                                                                       monkeypatch):
    """The refinement prompts its attention model as the edit prompts its SDS model, but only the SDS model's count
    was checked before the fit: a prompt the attention model reads fewer tokens of (here 40) had run the whole
    edit, then failed at the refinement."""
    from voxe_core.tiny_sd import build_tiny_stable_diffusion
    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from voxe_service.settings import get_settings
    from worker import tasks

    short = build_tiny_stable_diffusion(root / "short-sd")
    config = json.loads((short / "tokenizer" / "tokenizer_config.json").read_text())
    (short / "tokenizer" / "tokenizer_config.json").write_text(json.dumps({**config, "model_max_length": 40}))
    monkeypatch.setattr(get_settings(), "attention_model", str(short))
    scene = make_scene(client, dataset, root)
    prompt = "a mic wearing " + "big " * 30 + "sunglasses"  # 42 tokens with "a render of" and ", overhead view"
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": prompt, "mode": "local",
                                        "edit_words": ["sunglasses"]})
    assert job.status_code == 201, job.text
    assert tasks.reconstruct_task.apply(args=(job.json()["id"],)).get()["state"] == "failed"
    error = client.get(f"/v1/jobs/{job.json()['id']}").json()["error"]
    assert error.startswith("reconstruct: not started: the prompt 'a render of a mic wearing big") and error.endswith(
        f"tokens as the model's tokenizer reads it; its text encoder reads 40, its start and end tokens included: "
        f"shorten it (the attention model {str(short)!r})")
    global_job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": prompt})  # no attention pass
    with session_scope() as session:
        tasks._check_job_can_start(session.get(Job, global_job.json()["id"]), get_settings())


def test_a_local_job_whose_attention_tokenizer_cannot_be_read_fails_at_the_start_of_its_chain(root, client, dataset,
                                                                                             monkeypatch):
    """A damaged attention model (every file there, vocab.json cut short) had been skipped by the start-of-chain
    check, the job running its whole fit and edit before the refinement's load failed on the same file."""
    from voxe_core.tiny_sd import build_tiny_stable_diffusion
    from voxe_service.model_inventory import how_to_repair
    from voxe_service.settings import get_settings
    from worker import tasks

    damaged = build_tiny_stable_diffusion(root / "damaged-sd")
    vocab = damaged / "tokenizer" / "vocab.json"
    vocab.write_bytes(vocab.read_bytes()[: vocab.stat().st_size // 2])
    monkeypatch.setattr(get_settings(), "attention_model", str(damaged))
    scene = make_scene(client, dataset, root)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic wearing a party hat",
                                        "mode": "local", "edit_words": ["party hat"]})
    assert job.status_code == 201, job.text
    assert tasks.reconstruct_task.apply(args=(job.json()["id"],)).get()["state"] == "failed"
    error = client.get(f"/v1/jobs/{job.json()['id']}").json()["error"]
    assert error.startswith(f"reconstruct: not started: the attention model {str(damaged)!r} on this worker cannot "
                            "be read (OSError: tokenizer files unreadable: "), error
    assert API_SETTING.format("VOXE_ATTENTION_MODEL") in error
    # `hf download` keeps a cached file as it is: the copy is replaced (a hub id: downloaded with --force-download)
    assert f"replace the folder {str(damaged)!r} on the workers with an intact copy" in error and "hf download" not in error
    hub = how_to_repair("attention", "owner/model")
    assert f"`{download_command('owner/model')} --force-download`" in hub and "delete its folder there" in hub


def test_migration_0006_adds_the_models_column_and_removes_it(tmp_path):
    from alembic import command
    from sqlalchemy import inspect, text

    from service_helpers import database_at

    url = f"sqlite:///{tmp_path / 'm.db'}"
    config, engine = database_at(url, "0005_webhooks",
                                 "INSERT INTO worker_heartbeats (hostname, pid, queues, device, started_at, last_seen) "
                                 "VALUES ('old', 1, 'gpu', 'cpu', '2026-01-01', '2026-01-01')")
    command.upgrade(config, "0006_worker_models")
    with engine.connect() as conn:
        assert conn.execute(text("SELECT models FROM worker_heartbeats")).scalar_one() is None
    command.downgrade(config, "0005_webhooks")
    assert "models" not in {c["name"] for c in inspect(engine).get_columns("worker_heartbeats")}
    assert set(ROLES) == {"sds", "attention", "clip", "fid"}


def test_a_failed_smoke_test_model_build_leaves_nothing_and_the_next_one_completes(tmp_path):
    """build_once builds aside and renames into place: a build that fails half way leaves no folder behind."""
    from types import SimpleNamespace

    from worker.runtime import build_once

    settings = SimpleNamespace(model_dir=str(tmp_path))

    def failing(folder):
        (folder / "half.bin").write_bytes(b"x")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        build_once(settings, "tiny-sd", "model_index.json", failing)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".tiny.lock"]
    built = build_once(settings, "tiny-sd", "model_index.json", lambda folder: (folder / "model_index.json").write_text("{}"))
    assert built == tmp_path / "tiny-sd" and (built / "model_index.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".tiny.lock", "tiny-sd"]


def test_an_edit_word_the_attention_tokenizer_does_not_find_fails_at_the_start_of_its_chain(root, client):
    """The API finds edit words reading the prompt as CLIP's tokenizer should; where the real one reads it otherwise
    (a special token written out, characters newer than Python's Unicode tables, transformers 4.x's slow tokenizer)
    the job had run its whole fit and edit, then failed at the refinement. The worker finds each word with the
    attention model's tokenizer before the fit: here "<|endoftext|>" is one token, after which no word starts."""
    from voxe_service.models import Job
    from voxe_service.settings import get_settings
    from worker import tasks

    settings = get_settings()
    job = Job(mode="local", prompt="a <|endoftext|> hat on a mic", edit_words=["hat"], params={},
              sds_model=settings.sds_model, attention_model=settings.attention_model)
    with pytest.raises(tasks.CannotStart, match=r"^'hat' does not occur in the prompt 'a <\|endoftext\|> hat on a "
                                                 r"mic'.*\(the attention model "):
        tasks._check_job_can_start(job, settings)
    tasks._check_job_can_start(Job(mode="local", prompt="a hat on a mic", edit_words=["hat"], params={},
                                   sds_model=settings.sds_model, attention_model=settings.attention_model), settings)
