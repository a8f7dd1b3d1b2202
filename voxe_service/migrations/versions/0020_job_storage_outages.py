"""A job counts the runs of its stages a storage outage stopped in a column, as a scene counts its ingest's
(0018_ingest_storage_outages): the count had been read from the text of its ``requeued`` events. It doubles the pause
before the next such run's message goes back, and bounds the runs (VOXE_STORAGE_OUTAGE_MAX_RETRIES), as it does a
scene's ingest: a storage object answering 5xx every time had been retried for ever.

Jobs written before the column existed: counted from 0 (their outages' events, if any, are not read back). The
column keeps its server default (0), as the model declares it.

Revision ID: 0020_job_storage_outages
Revises: 0019_job_checkpoint_key
Create Date: 2026-12-07 00:20:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0020_job_storage_outages'
down_revision = '0019_job_checkpoint_key'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('storage_outages', sa.Integer(), server_default='0', nullable=False))


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_column('storage_outages')
