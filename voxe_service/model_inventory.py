"""Which models the workers have, known before a job needs them.

A worker checks at its start and at every heartbeat, offline and without
loading weights, which of its configured models are on its machine
(:func:`check_models`), and its heartbeat records the answer. The API reads those records: ``/readyz``
reports them, and a job whose model no worker has is refused at submission
(:func:`unavailable_models`); a job sent anyway (no worker had reported yet)
fails at the start of its chain, not after its reconstruction, with the same
message.

Examples:
    >>> job_models("local", "tiny", "tiny", {})
    {'sds': 'tiny', 'attention': 'tiny'}
    >>> sorted(job_models("evaluate", "", "", {"clip_model": "tiny", "fid_model": ""}))
    ['clip', 'fid']
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass

from voxe_core.constants import INCEPTION_FILE, inception_path
from voxe_core.guidance.loading import (CLIP_LAYOUT, DIFFUSERS_LAYOUT, clip_model_present, diffusers_model_present,
                                       download_command, local_path)
from voxe_service.models import EVALUATE
from voxe_service.settings import TINY_MODEL, Settings, model_label



@dataclass(frozen=True)
class ModelRole:
    """A model a stage loads: the setting that names it and what a copy of it holds."""

    name: str
    setting: str  # attribute of Settings
    # DIFFUSERS_LAYOUT: a Stable Diffusion, every component checked; CLIP_LAYOUT: a CLIP model, its files and weights
    # checked; None: the model is one file
    marker: str | None

    @property
    def variable(self) -> str:
        return f"VOXE_{self.setting.upper()}"


ROLES = {role.name: role for role in (
    ModelRole("sds", "sds_model", DIFFUSERS_LAYOUT),
    ModelRole("attention", "attention_model", DIFFUSERS_LAYOUT),
    ModelRole("clip", "clip_model", CLIP_LAYOUT),
    ModelRole("fid", "fid_model", None),
)}


def model_present(role: ModelRole, model: str, settings: Settings) -> bool:
    """Whether this machine has ``model`` for ``role`` (the smoke-test ``tiny`` models are built on demand: yes)."""
    if model == TINY_MODEL:
        return True
    if role.marker is None:  # FID: a TorchScript file, by default in the model dir
        # A zip archive: one cut short (a download written under its final name) lacks the directory at its end.
        return zipfile.is_zipfile(inception_path(model or settings.model_dir))
    return diffusers_model_present(model) if role.marker == DIFFUSERS_LAYOUT else clip_model_present(model)


def check_models(settings: Settings) -> dict[str, dict]:
    """role -> {"model": its setting, "present": bool} for every model this worker is configured with."""
    inventory = {}
    for role in ROLES.values():
        model = getattr(settings, role.setting)
        inventory[role.name] = {"model": model, "present": model_present(role, model, settings)}
    return inventory


def job_models(mode: str, sds_model: str, attention_model: str, params: dict) -> dict[str, str]:
    """role -> model for what a job of ``mode`` loads: an edit's SDS (and a local edit's attention) model,
    an evaluation's CLIP and FID models."""
    if mode == EVALUATE:
        return {"clip": params.get("clip_model", ""), "fid": params.get("fid_model", "")}
    models = {"sds": sds_model}
    if mode == "local":
        models["attention"] = attention_model
    return models


def submission_note(role_name: str) -> str:
    """Where a job's model comes from, so a fix lands where it counts: the API's setting when the job was submitted
    (a worker's own setting only chooses which model its heartbeat reports on)."""
    role = ROLES[role_name]
    other = ("the path of a TorchScript Inception file on the workers" if role.marker is None else
             f"a local folder on the workers holding {role.marker}")
    return (f"A job loads the model the API's {role.variable} named when the job was submitted (a worker's own "
            f"{role.variable} only chooses the model its heartbeat reports on): for new jobs the API's "
            f"{role.variable} may name another, e.g. {other}, or {role.variable}={TINY_MODEL}, the random-weight "
            "smoke-test model, which proves the plumbing only")


def how_to_provide(role_name: str, model: str) -> str:
    """What an operator does about a missing model: put it on the workers, or name another in the API's setting. A
    folder is filled, not downloaded: ``/models/sd`` had been advised ``hf download /models/sd``, no hub id."""
    role = ROLES[role_name]
    if role.marker is None:
        provide = (f"put the TorchScript Inception file at {model!r} on the workers" if model else
                   f"put {INCEPTION_FILE} in the workers' VOXE_MODEL_DIR")
    elif (folder := local_path(model)) is not None:
        provide = f"put the whole model ({role.marker}) in the folder {folder!r} on the workers"
    else:
        provide = (f"download it into the workers' Hugging Face cache (HF_HOME) with `{role_download(role, model)}` "
                   "on a machine with internet")
    return f"{provide}. {submission_note(role_name)}"


def role_download(role: ModelRole | str, model: str) -> str:
    """The `hf download` of hub id ``model`` fetching only the files that loading a ``role``'s model reads
    (``download_command``)."""
    role = ROLES[role] if isinstance(role, str) else role
    return download_command(model, clip=role.marker == CLIP_LAYOUT)


def how_to_repair(role_name: str, model: str) -> str:
    """What an operator does about a damaged copy of ``model`` (a hub id or a local folder; a file cut short):
    ``hf download`` alone keeps a file already in the cache as it is, damaged or not."""
    if (folder := local_path(model)) is not None:
        repair = f"replace the folder {folder!r} on the workers with an intact copy"
    else:
        repair = (f"download it again into the workers' Hugging Face cache (HF_HOME) with "
                  f"`{role_download(role_name, model)} --force-download` on a machine with internet, or delete its "
                  "folder there and download it")
    return f"{repair}. {submission_note(role_name)}"


def missing_message(role_name: str, model: str, where: str) -> str:
    return f"the {role_name} model {model_label(model) or '(default)'!r} is not on {where}: {how_to_provide(role_name, model)}"


def unavailable_models(needed: dict[str, str], inventories: dict[str, dict | None]) -> list[str]:
    """Messages for the models in ``needed`` (role -> model) that every worker reporting on them lacks.

    ``inventories`` is hostname -> what its heartbeat recorded (None: nothing yet).
    A model no worker has reported on is not refused: a worker configured for it
    may start later, and its chain then checks at its start.
    """
    messages = []
    for role, model in needed.items():
        reports = {host: inv[role]["present"] for host, inv in inventories.items()
                   if inv and inv.get(role, {}).get("model") == model}
        if reports and not any(reports.values()):
            messages.append(missing_message(role, model, f"any worker ({', '.join(sorted(reports))})"))
    return messages


def heartbeat_cutoff(settings: Settings):
    """Heartbeats older than this are from workers that stopped (three missed beats, at least 15 s)."""
    from datetime import timedelta

    from voxe_service.models import utcnow

    return utcnow() - timedelta(seconds=max(3 * settings.worker_heartbeat_s, 15))


def live_worker_models(session, settings: Settings) -> dict[str, dict | None]:
    """hostname -> the models its heartbeat recorded, for every worker heard from recently."""
    from sqlalchemy import select

    from voxe_service.models import WorkerHeartbeat

    rows = session.execute(select(WorkerHeartbeat.hostname, WorkerHeartbeat.models)
                           .where(WorkerHeartbeat.last_seen >= heartbeat_cutoff(settings)))
    return {hostname: models for hostname, models in rows}
