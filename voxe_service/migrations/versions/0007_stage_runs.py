"""Jobs record the run of a stage that holds them (token and lease) and how often they were re-queued; a
reconstruction records which run of its owner job fits it

Rows written before the columns existed: no run holds them (NULL), re-queued 0 times.

Revision ID: 0007_stage_runs
Revises: 0006_worker_models
Create Date: 2026-12-03 19:30:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0007_stage_runs'
down_revision = '0006_worker_models'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('reconstructions', schema=None) as batch_op:
        batch_op.add_column(sa.Column('owner_run_token', sa.String(length=32), nullable=True))
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('run_token', sa.String(length=32), nullable=True))
        batch_op.add_column(sa.Column('run_lease_until', sa.DateTime(timezone=True), nullable=True))
        batch_op.add_column(sa.Column('requeues', sa.Integer(), server_default='0', nullable=False))
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.alter_column('requeues', server_default=None)


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_column('requeues')
        batch_op.drop_column('run_lease_until')
        batch_op.drop_column('run_token')
    with op.batch_alter_table('reconstructions', schema=None) as batch_op:
        batch_op.drop_column('owner_run_token')
