"""A key's upload quota, read where bytes are stored: by the API on an upload, and by a mesh's ingest, whose
rendered views replace the (small) uploaded file and would otherwise pass the quota unchecked."""

from __future__ import annotations

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from voxe_service.models import PROCESSING, ApiKey, Scene
from voxe_service.settings import Settings


def lock_key(session: Session, key_id: str) -> None:
    """Serialise a key's quota checks until the transaction ends: PostgreSQL's row lock. SQLite's ``FOR UPDATE``
    locks nothing, and a check that reads before it writes (a mesh's ingest) had missed an upload landing between
    its read and its write: a write of the row (its name, unchanged) takes the database's write lock first."""
    if session.get_bind().dialect.name == "sqlite":
        session.execute(update(ApiKey).where(ApiKey.id == key_id).values(name=ApiKey.name))
    else:
        session.execute(select(ApiKey.id).where(ApiKey.id == key_id).with_for_update())


def upload_limit(key: ApiKey, settings: Settings) -> int:
    return key.max_upload_bytes or settings.max_upload_bytes_per_key


def stored_bytes(session: Session, key_id: str, excluding: str | None = None) -> int:
    """Bytes of the key's stored scenes (a failed scene's are 0), but for scene ``excluding``."""
    query = select(func.coalesce(func.sum(Scene.size_bytes), 0)).where(Scene.owner_key_id == key_id)
    if excluding is not None:
        query = query.where(Scene.id != excluding)
    return session.scalar(query) or 0


def ingest_over_quota(session: Session, scene_id: str, size: int, settings: Settings) -> str | None:
    """Why scene ``scene_id`` growing to ``size`` bytes at its ingest is over its key's upload quota (the key
    locked until the transaction ends, so racing ingests see each other's sizes); None when it fits."""
    scene = session.get(Scene, scene_id)
    key = session.get(ApiKey, scene.owner_key_id) if scene is not None and scene.state == PROCESSING else None
    if key is None:  # deleted, or failed meanwhile: not made ready, whatever its size
        return None
    lock_key(session, key.id)
    others, limit = stored_bytes(session, key.id, excluding=scene_id), upload_limit(key, settings)
    if others + size <= limit:
        return None
    return (f"quota of upload bytes exceeded: the mesh's rendered views take {size} bytes and key {key.name!r} "
            f"stores {others} bytes of other scenes, the limit is {limit} (VOXE_MAX_UPLOAD_BYTES_PER_KEY or the "
            "key's own); delete scenes to free space and upload it again")
