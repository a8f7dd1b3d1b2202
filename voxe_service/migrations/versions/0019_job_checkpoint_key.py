"""A job records the storage key of its live checkpoint: each checkpoint is stored under a key of its own
(``jobs/<id>/checkpoints/<run token>/<iteration>/<stage>.safetensors``) and recorded only while its run holds the job,
so a stalled run's late upload can no longer overwrite the checkpoint of the run that took the job over.

Jobs written before the column existed stored theirs at the one fixed key ``checkpoints/edit.safetensors``: a job not
ended records that key, for its next run to resume from (it starts over where nothing is stored there).

Revision ID: 0019_job_checkpoint_key
Revises: 0018_ingest_storage_outages
Create Date: 2026-12-07 00:40:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0019_job_checkpoint_key'
down_revision = '0018_ingest_storage_outages'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('checkpoint_key', sa.String(length=512), nullable=True))
    op.execute("UPDATE jobs SET checkpoint_key = 'jobs/' || id || '/checkpoints/edit.safetensors' "
               "WHERE state IN ('queued', 'running')")


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_column('checkpoint_key')
