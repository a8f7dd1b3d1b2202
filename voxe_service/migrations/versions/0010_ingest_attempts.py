"""A scene counts the runs of its ingest, so an upload whose ingest kills its workers fails instead of looping

Scenes written before the column existed: 0 runs. The column keeps its server default (0), as the model
declares it: on SQLite, taking it off would rebuild the scenes table (see 0009_byte_sizes).

Revision ID: 0010_ingest_attempts
Revises: 0009_byte_sizes
Create Date: 2026-12-06 12:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0010_ingest_attempts'
down_revision = '0009_byte_sizes'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.add_column(sa.Column('ingest_attempts', sa.Integer(), server_default='0', nullable=False))


def downgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.drop_column('ingest_attempts')
