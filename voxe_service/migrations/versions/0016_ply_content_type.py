"""PLY artifacts recorded before the worker named their type (application/octet-stream) get model/ply, the type it
records for them now, so a download's Content-Type does not depend on when its job ran. Downgrading gives them back
the type the earlier worker recorded.

Revision ID: 0016_ply_content_type
Revises: 0015_owner_index_prefix
Create Date: 2026-12-06 18:45:00
"""

from __future__ import annotations

from alembic import op

revision = '0016_ply_content_type'
down_revision = '0015_owner_index_prefix'
branch_labels = None
depends_on = None


def _retype(old: str, new: str) -> None:
    op.execute(f"UPDATE artifacts SET content_type = '{new}' "
               f"WHERE content_type = '{old}' AND lower(name) LIKE '%.ply'")


def upgrade() -> None:
    _retype('application/octet-stream', 'model/ply')


def downgrade() -> None:
    _retype('model/ply', 'application/octet-stream')
