"""Evaluation jobs and sweeps: the jobs an evaluation scores, its metrics, the batch a job belongs to

Revision ID: 0003_evaluation
Revises: 0002_access
Create Date: 2026-12-01 14:55:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0003_evaluation'
down_revision = '0002_access'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('source_job_ids', sa.JSON(), nullable=True))
        batch_op.add_column(sa.Column('result', sa.JSON(), nullable=True))
        batch_op.add_column(sa.Column('batch_id', sa.String(length=32), nullable=True))
        batch_op.create_index(batch_op.f('ix_jobs_batch_id'), ['batch_id'], unique=False)


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_jobs_batch_id'))
        batch_op.drop_column('batch_id')
        batch_op.drop_column('result')
        batch_op.drop_column('source_job_ids')
