"""Loading diffusers-layout weights: hub ids from the local cache or folders, and the clear error when they are missing.

Real weights are never substituted: a model that cannot be loaded is a
:class:`ModelNotAvailableError` naming it and saying how to provide it.
"""

from __future__ import annotations

import json
import os
from typing import Callable

from voxe_core.constants import TINY_MODEL, TINY_MODEL_NAME

DIFFUSERS_LAYOUT = "model_index.json, unet/, vae/, text_encoder/, tokenizer/, scheduler/"
DIFFUSERS_FILES = ("model_index.json", "unet/config.json", "vae/config.json", "text_encoder/config.json",
                   "tokenizer/vocab.json", "tokenizer/merges.txt", "scheduler/scheduler_config.json")
"""The small files loading reads of every diffusers-layout Stable Diffusion: each component's config, the vocabulary."""
WHOLE_FOLDERS = ("tokenizer", "scheduler")
"""The components loading reads every file of (those of :data:`DIFFUSERS_FILES` and what else they hold)."""
COMPONENT_CONFIGS = tuple(name for name in DIFFUSERS_FILES if "/" in name and name.endswith("config.json"))
"""The configs each component is built from (checked by :func:`component_config_fault` before loading)."""
WEIGHTED_COMPONENTS = ("unet", "vae", "text_encoder")
"""The components with weights (``*.safetensors`` or ``*.bin`` inside their folder, or all the shards its
``*.index.json`` names)."""
CLIP_FILES = ("config.json", "preprocessor_config.json")
"""The configs loading a CLIP model reads (``voxe_core.evaluate.ClipScorer``): the model's and its image processor's."""
CLIP_TOKENIZERS = (("vocab.json", "merges.txt"), ("tokenizer.json",))
"""The files of a CLIP tokenizer, one set of them whole (transformers 5 reads ``tokenizer.json`` alone; 4's
``CLIPTokenizer`` needs the first)."""
CLIP_TOKENIZER_CONFIGS = ("tokenizer_config.json", "special_tokens_map.json")
"""The tokenizer's settings a CLIP tokenizer reads where they are (its 77-token ``model_max_length`` among them)."""
CLIP_WEIGHTS = ("model.safetensors", "pytorch_model.bin")
"""The weights files transformers loads a model from, any one of them whole, or its shards an index of that name
plus ``.index.json`` lists."""
CLIP_LAYOUT = (f"{', '.join(CLIP_FILES)}, its tokenizer ({' and '.join(CLIP_TOKENIZERS[0])}, or "
               f"{CLIP_TOKENIZERS[1][0]}) and its weights ({' or '.join(CLIP_WEIGHTS)}, or their shards)")


class ModelNotAvailableError(RuntimeError):
    """The requested diffusion weights cannot be loaded (not cached, offline, or incomplete)."""


def offline_env() -> bool:
    """Whether the environment forbids the hub (``HF_HUB_OFFLINE=1``): the default of ``local_files_only``."""
    return os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in ("1", "true", "yes", "on")


def not_available_message(model: str, cause: BaseException | None, offline: bool = True, cached: bool = False,
                          revision: str | None = None) -> str:
    """The error text for missing weights: which model, how to get it, and what failed underneath. A folder is
    told to hold the model (a hub download of "./models/sd" had been its remedy), a hub id how to cache it, or, where
    downloads were allowed (``offline`` False), to check its id: a mistyped one had been told it was "not available
    offline" and to download it, though the hub had been asked and has no such model. A hub id whose files are all in
    the cache (``cached``) failed on reading them, and is told to fetch them again: a damaged weights file had been
    told to check the model id (or that the model was not available offline). A ``revision`` other than main is in
    each `hf download` advised (it had fetched main again, and the revision loaded stayed as it was), which fetches
    only the files loading reads (:func:`download_command`); `huggingface-cli`, gone from huggingface_hub 1.0 (which
    transformers 5 needs), is no longer advised."""
    download = download_command(model, revision=revision)
    if model == TINY_MODEL and local_path(model) is None:
        msg = f"Stable Diffusion weights '{model}' are not available: {tiny_model_note('`voxe build-tiny-model DIR`')}."
    elif cached and local_path(model) is None:
        msg = (
            f"Stable Diffusion weights '{model}' are in the Hugging Face cache (HF_HOME) but could not be read: a "
            f"file of them is damaged (a download cut short, a disk error) or not this model's; download them again "
            f"with `{download} --force-download`."
        )
    elif local_path(model) is not None:
        msg = (
            f"Stable Diffusion weights '{model}' are not available: that local folder must hold the whole model in "
            f"the diffusers layout ({DIFFUSERS_LAYOUT}, each with its config and weights); or name a hub id "
            f"whose weights are in the Hugging Face cache (HF_HOME)."
        )
    elif not offline:
        msg = (
            f"Stable Diffusion weights '{model}' could not be fetched from the Hugging Face hub"
            f"{no_folder_note(model)}: check the model id (a private or gated model also needs a token: "
            f"`hf auth login`) and this machine's connection, or download them with `{download}` on a "
            f"machine with internet and point HF_HOME at that cache, or pass a local folder in the diffusers layout "
            f"({DIFFUSERS_LAYOUT})."
        )
    else:
        msg = (
            f"Stable Diffusion weights '{model}' are not available offline{no_folder_note(model)}: download them "
            f"once with `{download}` on a machine with internet and "
            f"point HF_HOME at that cache, or pass a local folder in the diffusers layout ({DIFFUSERS_LAYOUT})."
        )
    if cause is not None:
        detail = " ".join(str(cause).split())
        if len(detail) > 400:
            detail = detail[:400] + "..."
        msg += f" Underlying error: {type(cause).__name__}: {detail}"
    return msg


def tiny_model_note(build: str) -> str:
    """What ``TINY_MODEL`` names where a model is loaded here, and how to build that model (``build``): it had been
    told to `hf download tiny`, no hub id."""
    return (f"'{TINY_MODEL}' is the service's name for its random-weight smoke-test model, which it builds in code; "
            f"it is no hub id, and there is no folder {TINY_MODEL!r} here: write one with {build} and pass that folder "
            "(it proves the plumbing only, never quality)")


SMOKE_TEST_MODEL_NOTE = ("a random-weight smoke-test Stable Diffusion (voxe build-tiny-model): what is made with it "
                         "proves the plumbing only and says nothing about edit quality")
"""What a run with a folder :func:`smoke_test_model` recognises says of it, at its start and in what it writes."""


def smoke_test_model(model: str) -> bool:
    """Whether ``model`` is a folder ``voxe_core.tiny_sd`` wrote (random weights): its model_index.json names it
    :data:`~voxe_core.constants.TINY_MODEL_NAME`, as every build's has. Read without torch, before the model loads: a
    run with it had said nothing of its results being noise."""
    try:
        with open(os.path.join(os.path.expanduser(model), "model_index.json"), encoding="utf-8") as file:
            index = json.load(file)
    except (OSError, ValueError):
        return False
    return isinstance(index, dict) and index.get("_name_or_path") == TINY_MODEL_NAME


def smoke_test_note(model: str) -> str | None:
    """What a run with ``model`` records in what it writes where :func:`smoke_test_model` recognises it; else None."""
    return f"{model} is {SMOKE_TEST_MODEL_NOTE}" if smoke_test_model(model) else None


def local_path(model: str) -> str | None:
    """The folder ``model`` names ("~" expanded: absolute, relative, existing, or no hub id: "models/sd/v1", which
    diffusers too reads as a folder first and then, as a hub id, fails on), or None for a hub id."""
    path = os.path.expanduser(model)
    if os.path.isabs(path) or model.startswith(".") or os.path.exists(path) or not _hub_id_form(model):
        return path
    return None


def _hub_id_form(model: str) -> bool:
    """Whether ``model`` is written as a hub id can be: ``name`` or ``owner/name`` (the hub's own rule)."""
    from huggingface_hub.errors import HFValidationError
    from huggingface_hub.utils import validate_repo_id

    try:
        validate_repo_id(model)
    except HFValidationError:
        return False
    return True


def no_folder_note(model: str) -> str:
    """For a hub id ``owner/name`` (:func:`local_path` None) whose owner is a folder here ("models/sd" beside a
    models/ without sd): that there is no such folder either, the path most likely meant (it had been told only how
    to fetch it from the hub); "" otherwise."""
    owner, _, name = model.partition("/")
    if local_path(model) is not None or not os.path.isdir(owner):
        return ""
    return f" (nor is there a folder {model}: {os.path.abspath(owner)} holds no {name!r})"


def model_file(model: str, filename: str, revision: str | None = None) -> str | None:
    """Where ``filename`` of ``model`` (a folder, or a hub id in the Hugging Face cache) is on this machine, or None.

    Offline and cheap: it looks the file up and reads nothing, so a worker can say
    at its start which models it has without loading them.

    Examples:
        >>> model_file("no-such-owner/no-such-model", "model_index.json") is None
        True
    """
    folder = local_path(model)
    if folder is not None:
        path = os.path.join(folder, filename)
        return path if os.path.isfile(path) else None
    from huggingface_hub import try_to_load_from_cache
    from huggingface_hub.errors import HFValidationError

    try:
        path = try_to_load_from_cache(model, filename, revision=revision)
    except HFValidationError:  # not a valid hub id either
        return None
    return path if isinstance(path, str) else None


def diffusers_model_present(model: str, revision: str | None = None) -> bool:
    """Whether the diffusers-layout ``model`` (a folder, or a hub id in the Hugging Face cache, at ``revision``: its
    main branch by default) is whole on this machine.

    Offline and cheap, no weights read: every file of :data:`DIFFUSERS_FILES` and a
    weights file of each of :data:`WEIGHTED_COMPONENTS`. ``model_index.json`` alone is
    not enough: a download cut short leaves it in the cache's snapshot without the
    weights that had not arrived, and the model would fail only when a job loads it.
    Nor is one shard of a sharded component: its index arrives before the shards it names.
    The parts are :func:`missing_parts`', those loading reads: a folder without ``model_index.json`` had been
    reported missing by the workers while the CLI loaded it.
    """
    folder = model_folder(model, revision)
    return folder is not None and not missing_parts(folder)


def model_folder(model: str, revision: str | None = None) -> str | None:
    """The folder of the diffusers-layout ``model`` on this machine: the local folder, or the cached snapshot of the
    hub's ``revision``, where it holds a file of :data:`DIFFUSERS_FILES`; None otherwise."""
    for name in DIFFUSERS_FILES:
        if (path := model_file(model, name, revision)) is not None:
            return path[:-len(name) - 1]  # (the file's path is the folder's joined with its name)
    return None


def missing_parts(folder: str) -> list[str]:
    """The parts of the diffusers-layout model in ``folder`` that loading reads and are not there: each file of
    :data:`DIFFUSERS_FILES` but ``model_index.json`` (loading reads the components alone) by its path, and "weights in <component>/" for each of :data:`WEIGHTED_COMPONENTS` without them (sharded: every
    shard of every ``*.index.json``). A variant's weights alone (``diffusion_pytorch_model.fp16.safetensors``, what a
    download of the fp16 files leaves) are not the component's: loading reads no variant, and had failed on them with
    "no file named diffusion_pytorch_model.bin found in directory <the model's folder>", the model counted whole."""

    def weights_missing(component: str) -> str | None:
        path = os.path.join(folder, component)
        names = sorted(os.listdir(path)) if os.path.isdir(path) else []
        indexes = [name for name in names if name.endswith(".index.json")]
        if indexes:
            whole = all(shards_present(os.path.join(path, index)) for index in indexes)
        else:
            whole = any(name.endswith((".safetensors", ".bin")) and name.count(".") == 1
                        and os.path.isfile(os.path.join(path, name)) for name in names)
        if whole:
            return None
        variants = [name for name in names if name.endswith((".safetensors", ".bin")) and name.count(".") > 1]
        return f"weights in {component}/" + (f" (only {', '.join(variants)}: a variant's, which loading does not "
                                             "read)" if variants and not indexes else "")

    return ([name for name in DIFFUSERS_FILES
             if name != "model_index.json" and not os.path.isfile(os.path.join(folder, name))]
            + [part for component in WEIGHTED_COMPONENTS if (part := weights_missing(component)) is not None])


def clip_model_present(model: str) -> bool:
    """Whether the CLIP ``model`` (a folder, or a hub id in the Hugging Face cache) is whole on this machine: every
    file of :data:`CLIP_FILES`, one set of :data:`CLIP_TOKENIZERS` and one of :data:`CLIP_WEIGHTS`, offline and no
    weights read. ``config.json`` alone had counted: a download cut short (the weights arrive last) was offered by the
    workers, and an evaluation sweep failed loading it only after all its edits had run."""
    config = model_file(model, "config.json")
    if config is None:
        return False
    folder = os.path.dirname(config)  # the local folder, or the cached snapshot of the hub's revision

    def has(name: str) -> bool:
        return os.path.isfile(os.path.join(folder, name))

    tokenizers = CLIP_TOKENIZERS if _transformers_major() >= 5 else CLIP_TOKENIZERS[:1]
    return (all(map(has, CLIP_FILES)) and any(all(map(has, files)) for files in tokenizers)
            and any(has(weights) or shards_present(os.path.join(folder, f"{weights}.index.json"))
                    for weights in CLIP_WEIGHTS))


def shards_present(index_path: str) -> bool:
    """Whether the weights index at ``index_path`` (``*.index.json``) reads and every shard its ``weight_map`` names is
    beside it: the index arrives before its shards, so it alone does not make the weights whole."""
    try:
        with open(index_path, encoding="utf-8") as index:
            shards = set(json.load(index)["weight_map"].values())
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False
    folder = os.path.dirname(index_path)
    return bool(shards) and all(isinstance(shard, str) and os.path.isfile(os.path.join(folder, shard))
                                for shard in shards)


def _transformers_major() -> int:
    """The installed transformers' major version (0 when it is not installed or reads otherwise), read from its
    metadata: importing it takes seconds."""
    try:
        return int(_transformers_version().split(".")[0])
    except ValueError:
        return 0


def _transformers_version() -> str:
    """The installed transformers' version ("" when it is not installed), from its metadata."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("transformers")
    except PackageNotFoundError:
        return ""


def loading_errors() -> tuple[type[BaseException], ...]:
    """The exceptions by which loading says weights are missing or damaged (caught and turned into ours).

    Missing: the hub's errors and OSError. Damaged: safetensors' SafetensorError (a truncated or
    corrupt weights file), and the ValueError / RuntimeError ``from_pretrained`` raises for an
    unreadable JSON file, torch archive or weights of another shape. Catch them around loading
    alone, and let :func:`is_out_of_memory` ones through: an allocation failure is a RuntimeError too.
    """
    errors: list[type[BaseException]] = [OSError, ValueError, RuntimeError]
    try:
        from safetensors import SafetensorError

        errors.append(SafetensorError)
    except ImportError:  # pragma: no cover - safetensors ships with transformers and diffusers
        pass
    try:
        from huggingface_hub.errors import HFValidationError, HfHubHTTPError

        errors += [HFValidationError, HfHubHTTPError]
    except ImportError:  # pragma: no cover - very old huggingface_hub
        pass
    try:
        import httpx

        errors.append(httpx.HTTPError)
    except ImportError:  # pragma: no cover
        pass
    return tuple(errors)


def is_out_of_memory(exc: BaseException) -> bool:
    """A failed allocation (CUDA's OutOfMemoryError, the CPU allocator's RuntimeError): the machine is short of
    memory, which ``loading_errors`` would otherwise report as a missing model."""
    import torch

    return isinstance(exc, (MemoryError, torch.cuda.OutOfMemoryError)) or "DefaultCPUAllocator" in str(exc)


def component_config_fault(model: str, revision: str | None = None) -> str | None:
    """What makes a component config of ``model`` on this machine unloadable, naming the file, or None.

    The libraries build each component from its config unchecked: a ``vae/config.json`` holding ``null``, a
    ``text_encoder/config.json`` holding a list or a ``hidden_act`` this transformers lacks had escaped loading as a
    TypeError or KeyError naming no model. Those are caught here, not by widening :func:`loading_errors`, which would
    report the libraries' own bugs as missing weights. A config that is absent or no JSON at all is left to loading,
    which reports it (or, for a hub id not cached, downloads it).
    """
    for name in COMPONENT_CONFIGS:
        path = model_file(model, name, revision)
        if path is None:
            continue
        try:
            with open(path, encoding="utf-8") as file:
                config = json.load(file)
        except (OSError, ValueError):
            continue
        if not isinstance(config, dict):
            return f"{name} is not a JSON object: it holds {json.dumps(config)[:60]}"
        if name == "text_encoder/config.json" and "hidden_act" in config:
            from transformers.activations import ACT2FN

            activation = config["hidden_act"]
            if not isinstance(activation, str) or activation not in ACT2FN:
                return (f"{name} names hidden_act {activation!r}, an activation this transformers "
                        f"({_transformers_version()}) does not have")
    return None


def load_clip_tokenizer(model: str, **kwargs):
    """``CLIPTokenizer.from_pretrained(model, **kwargs)``; the bare Exception the tokenizers library raises for an
    unreadable vocab.json or merges.txt ("Error while initializing BPE") becomes an OSError, a damaged model."""
    from transformers import CLIPTokenizer

    try:
        return CLIPTokenizer.from_pretrained(model, **kwargs)
    except loading_errors():
        raise
    except Exception as exc:  # noqa: BLE001 - tokenizers' Rust errors have no type of their own
        raise OSError(f"tokenizer files unreadable: {exc}") from exc


def hub_download_bytes(model: str, revision: str | None = None) -> int | None:
    """Bytes of the files of hub model ``model`` (at ``revision``, main by default) loading fetches
    (:func:`files_loaded`), or None when the hub cannot say (offline, unknown id). The whole repository's had been announced: CompVis/stable-diffusion-v1-4's single-file
    checkpoints, fp16, non-EMA and Flax weights, ten times what a load fetches."""
    from huggingface_hub import HfApi

    try:
        info = HfApi().model_info(model, revision=revision, files_metadata=True)
    except loading_errors():
        return None
    sizes = {s.rfilename: s.size or 0 for s in info.siblings or []}
    return sum(sizes[name] for name in files_loaded(list(sizes))) or None


def files_loaded(names: list[str]) -> list[str]:
    """Those of a diffusers-layout repository's files ``names`` that loading fetches: the small files of
    :data:`DIFFUSERS_FILES` and the other files of ``tokenizer/`` and ``scheduler/``, and for each of
    :data:`WEIGHTED_COMPONENTS` the weights it reads, as the libraries choose them: safetensors before a torch
    archive, a whole file before shards (an index and every shard beside it), never a variant's (``*.fp16.*``).

    Examples:
        >>> files_loaded(["unet/config.json", "unet/diffusion_pytorch_model.bin", "sd-v1-4.ckpt",
        ...               "unet/diffusion_pytorch_model.safetensors", "unet/diffusion_pytorch_model.fp16.safetensors"])
        ['unet/config.json', 'unet/diffusion_pytorch_model.safetensors']
    """
    whole = tuple(f"{folder}/" for folder in WHOLE_FOLDERS)
    chosen = [name for name in names if name in DIFFUSERS_FILES or name.startswith(whole)
              or name in COMPONENT_CONFIGS]
    for component in WEIGHTED_COMPONENTS:
        inside = [name[len(component) + 1:] for name in names if name.startswith(component + "/")]
        for suffix in (".safetensors", ".bin"):
            whole = [name for name in inside if name.endswith(suffix) and name.count(".") == 1 and "-of-" not in name]
            index = [name for name in inside if name.endswith(suffix + ".index.json") and name.count(".") == 3]
            shards = [name for name in inside if name.endswith(suffix) and name.count(".") == 1 and "-of-" in name]
            picked = whole[:1] or (index + shards if index else [])
            if picked:
                chosen += [f"{component}/{name}" for name in picked]
                break
    return chosen


def download_patterns(clip: bool = False) -> tuple[list[str], list[str]]:
    """The ``--include`` and ``--exclude`` globs of an `hf download` fetching what loading reads of a diffusers-layout
    model (``clip``: a CLIP one), from the lists loading checks: a bare
    `hf download stabilityai/stable-diffusion-2-base` had fetched the whole repository (fp16, Flax and single-file
    checkpoints: tens of GB). A component's weights are its whole files and shards of either format, never a
    variant's (``*.fp16.safetensors``); where a repository holds both formats the torch archives come too, which
    loading (safetensors first) then leaves unread.

    Examples:
        >>> download_patterns(clip=True)[0][:3]
        ['config.json', 'preprocessor_config.json', 'vocab.json']
    """
    suffixes = (".safetensors", ".bin")
    exclude = [f"*.*{suffix}" for suffix in suffixes]  # (a variant's name has a dot more: *.fp16.safetensors)
    if clip:
        tokenizer = dict.fromkeys(name for files in CLIP_TOKENIZERS for name in files)
        return [*CLIP_FILES, *tokenizer, *CLIP_TOKENIZER_CONFIGS,
                *(pattern for weights in CLIP_WEIGHTS for pattern in (
                    weights, f"{weights}.index.json", weights.replace(".", "-*-of-*.", 1)))], exclude
    return ([name for name in DIFFUSERS_FILES if name.split("/")[0] not in WHOLE_FOLDERS]
            + [f"{folder}/*" for folder in WHOLE_FOLDERS]
            + [f"{component}/*{suffix}{index}" for component in WEIGHTED_COMPONENTS for suffix in suffixes
               for index in ("", ".index.json")]), exclude


def download_command(model: str, clip: bool = False, revision: str | None = None) -> str:
    """`hf download` of the files of hub id ``model`` (at ``revision``: main when None or "main") that loading reads,
    :func:`download_patterns`' (``clip``: a CLIP model's), in the `hf` CLI's syntax (one ``--include`` a pattern).

    Examples:
        >>> download_command("owner/clip", clip=True, revision="v2")[:75]
        'hf download owner/clip --revision v2 --include config.json --include prepro'
    """
    import shlex

    include, exclude = download_patterns(clip)
    return " ".join([f"hf download {model}" + (f" --revision {revision}" if revision not in (None, "main") else "")]
                    + [f"--include {shlex.quote(pattern)}" for pattern in include]
                    + [f"--exclude {shlex.quote(pattern)}" for pattern in exclude])


def download_notice(model: str, local_files_only: bool, size_of: Callable[[str], int | None] | None = None,
                    revision: str | None = None) -> str | None:
    """What a user should see before ``model`` is fetched from the hub; None when nothing will be downloaded.

    A download happens only for a hub id whose ``revision`` (main by default) is not whole in the local cache
    (:func:`diffusers_model_present`) while downloads are allowed: a revision not cached had been fetched unannounced
    where main was. ``size_of`` asks the hub for the model's bytes (:func:`hub_download_bytes` of that revision by
    default; a parameter so it can be given another source).

    Examples:
        >>> download_notice("owner/model", local_files_only=False, size_of=lambda model: 5_210_000_000)
        'downloading owner/model (5.2 GB)'
        >>> download_notice("owner/model", local_files_only=True) is None
        True
    """
    if local_files_only or local_path(model) is not None or diffusers_model_present(model, revision):
        return None
    size = size_of(model) if size_of is not None else hub_download_bytes(model, revision)
    return f"downloading {model} ({size / 1e9:.1f} GB)" if size else f"downloading {model} (size unknown)"


def load_stable_diffusion(model: str, dtype, local_files_only: bool | None = None, revision: str | None = None,
                          on_message: Callable[[str], None] | None = None):
    """(unet, vae, text_encoder, tokenizer, scheduler) of the diffusers-layout ``model`` in ``dtype``.

    ``model`` is a hub id (from the Hugging Face cache, see ``HF_HOME``) or a local
    folder ("~" expanded); ``local_files_only`` defaults to :func:`offline_env`. ``on_message`` hears
    :func:`download_notice` before a first-use download, so the wait is not silent. Raises
    :class:`ModelNotAvailableError` naming the model when anything is missing.
    """
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from diffusers.utils import is_accelerate_available
    from transformers import CLIPTextModel

    if local_files_only is None:
        local_files_only = offline_env()
    kwargs = {"local_files_only": bool(local_files_only)}
    if revision is not None:
        kwargs["revision"] = revision

    folder = local_path(model)
    if folder is not None and os.path.isfile(folder):  # (it had been told "no folder <the file>")
        raise ModelNotAvailableError(not_available_message(model, NotADirectoryError(
            f"{folder} is a file, not a folder: a single-file checkpoint (.safetensors, .ckpt) is not read here; "
            "convert it to the diffusers layout first (diffusers' StableDiffusionPipeline.from_single_file(file)"
            ".save_pretrained(folder))")))
    if folder is not None and not os.path.isdir(folder):
        raise ModelNotAvailableError(not_available_message(model, FileNotFoundError(f"no folder {folder}")))
    # Named before loading: the libraries had said "no file named config.json found in directory <the folder>" for a
    # missing vae/, or built a default 512-wide text encoder without its config and failed on the weights' shapes,
    # after a table of every layer on stderr.
    if folder is not None and (missing := missing_parts(folder)):
        raise ModelNotAvailableError(not_available_message(model, FileNotFoundError(
            f"the folder lacks {', '.join(missing)}")))
    # A hub id's cached snapshot too, where nothing will be fetched: one without unet/ had been told "owner/sd does
    # not appear to have a file named config.json", naming no part
    if (folder is None and local_files_only and (snapshot := model_folder(model, revision)) is not None
            and (missing := missing_parts(snapshot))):
        raise ModelNotAvailableError(not_available_message(model, FileNotFoundError(
            f"its snapshot in the cache ({snapshot}) lacks {', '.join(missing)}"), revision=revision))
    source = model if folder is None else folder
    fault = component_config_fault(model, revision)
    if fault is not None:
        raise ModelNotAvailableError(not_available_message(model, ValueError(fault), revision=revision))
    notice = download_notice(model, bool(local_files_only), revision=revision) if on_message is not None else None
    if notice is not None:
        on_message(notice)

    # diffusers' default low_cpu_mem_usage=True needs accelerate (no dependency of ours): without it diffusers
    # falls back to False, warning at every load of the UNet and the VAE; asking for what it would do says nothing.
    unet_vae = {**kwargs, "low_cpu_mem_usage": is_accelerate_available()}
    try:
        unet = UNet2DConditionModel.from_pretrained(source, subfolder="unet", torch_dtype=dtype, **unet_vae)
        vae = AutoencoderKL.from_pretrained(source, subfolder="vae", torch_dtype=dtype, **unet_vae)
        text_encoder = CLIPTextModel.from_pretrained(source, subfolder="text_encoder", dtype=dtype, **kwargs)
        tokenizer = load_clip_tokenizer(source, subfolder="tokenizer", **kwargs)
        scheduler = DDIMScheduler.from_pretrained(source, subfolder="scheduler", **kwargs)
    except loading_errors() as exc:
        if is_out_of_memory(exc):
            raise
        cached = folder is None and diffusers_model_present(model, revision)  # (nothing was to be fetched)
        raise ModelNotAvailableError(
            not_available_message(model, exc, bool(local_files_only), cached, revision)) from exc
    if not tokenizer_fits(tokenizer, text_encoder.config.vocab_size):
        raise ModelNotAvailableError(
            not_available_message(
                model,
                OSError(f"tokenizer/ has {len(tokenizer)} tokens but the text encoder expects "
                        f"{text_encoder.config.vocab_size}: tokenizer files missing or wrong"),
            )
        )
    return unet, vae, text_encoder, tokenizer, scheduler


def tokenizer_fits(tokenizer, vocab_size: int) -> bool:
    """Whether a loaded CLIP tokenizer is its text model's (``vocab_size`` tokens, a few added ones allowed).

    transformers >= 5 builds a tokenizer of only the special tokens, instead of failing, when
    vocab.json / merges.txt are missing: every prompt would then encode alike.
    """
    return len(tokenizer.all_special_tokens) < len(tokenizer) <= vocab_size + 16
