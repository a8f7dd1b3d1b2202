"""Byte sizes are 64-bit: scenes.size_bytes, artifacts.size and reconstructions.grid_size

A PostgreSQL integer ends at 2 GiB - 1, the default upload limit is 2 GiB and a key's quota 50 GiB: a
scene of 2 GiB or more failed to store ("integer out of range"). SQLite's INTEGER is already 64-bit, and
rebuilding its tables (batch mode) would cascade-delete their jobs, so SQLite is left as it is.

Revision ID: 0009_byte_sizes
Revises: 0008_scene_backbone
Create Date: 2026-12-05 14:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0009_byte_sizes'
down_revision = '0008_scene_backbone'
branch_labels = None
depends_on = None

COLUMNS = (("scenes", "size_bytes", False), ("artifacts", "size", False), ("reconstructions", "grid_size", True))


def _retype(to: sa.types.TypeEngine, from_: sa.types.TypeEngine) -> None:
    if op.get_bind().dialect.name == "sqlite":
        return
    for table, column, nullable in COLUMNS:
        op.alter_column(table, column, type_=to, existing_type=from_, existing_nullable=nullable)


def upgrade() -> None:
    _retype(sa.BigInteger(), sa.Integer())


def downgrade() -> None:
    _retype(sa.Integer(), sa.BigInteger())
