"""Worker heartbeats record which models the worker has (checked offline at its start)

Rows written before the column existed hold NULL: a worker that has not said which models it has.

Revision ID: 0006_worker_models
Revises: 0005_webhooks
Create Date: 2026-12-09 09:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0006_worker_models'
down_revision = '0005_webhooks'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('worker_heartbeats', schema=None) as batch_op:
        batch_op.add_column(sa.Column('models', sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('worker_heartbeats', schema=None) as batch_op:
        batch_op.drop_column('models')
