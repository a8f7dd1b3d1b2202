"""A scene counts the re-sends of its ingest whose message was taken as lost, so the reaper doubles its wait before
the next, as it does a job's: one behind a long backlog (or with every worker down) had been sent again each window

Scenes written before the column existed: never sent again so (0). The column keeps its server default (0), as the
model declares it (see 0010_ingest_attempts).

Revision ID: 0017_lost_ingest_resends
Revises: 0016_ply_content_type
Create Date: 2026-12-06 19:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0017_lost_ingest_resends'
down_revision = '0016_ply_content_type'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.add_column(sa.Column('lost_ingest_resends', sa.Integer(), server_default='0', nullable=False))


def downgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.drop_column('lost_ingest_resends')
