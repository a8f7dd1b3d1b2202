"""A scene counts the runs of its ingest a storage outage stopped apart from its ingest attempts: they no longer use
up the attempts (an outage every scene meets alike had failed the scenes ingesting through it at the limit), but
still double the pause before the next run's message goes back.

Scenes written before the column existed: none so stopped (0). The column keeps its server default (0), as the
model declares it (see 0010_ingest_attempts).

Revision ID: 0018_ingest_storage_outages
Revises: 0017_lost_ingest_resends
Create Date: 2026-12-06 22:20:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0018_ingest_storage_outages'
down_revision = '0017_lost_ingest_resends'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.add_column(sa.Column('ingest_storage_outages', sa.Integer(), server_default='0', nullable=False))


def downgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.drop_column('ingest_storage_outages')
