"""A scene records what reconstruction backbone "auto" means for it, decided at its ingest

Scenes ingested before the column existed: NULL (their jobs resolve "auto" from the images they load).

Revision ID: 0008_scene_backbone
Revises: 0007_stage_runs
Create Date: 2026-12-03 22:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0008_scene_backbone'
down_revision = '0007_stage_runs'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.add_column(sa.Column('backbone', sa.String(length=16), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.drop_column('backbone')
