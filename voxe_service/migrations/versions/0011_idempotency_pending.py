"""An Idempotency-Key record says whether the request that wrote it has answered: until then the broker may still
refuse what it created (a 503 withdraws it), so a retry meanwhile is answered 409 rather than replaying it

Records written before the column existed: answered. The column keeps its server default (false), as the model
declares it: on SQLite, taking it off would rebuild the table (see 0009_byte_sizes).

Revision ID: 0011_idempotency_pending
Revises: 0010_ingest_attempts
Create Date: 2026-12-05 19:50:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0011_idempotency_pending'
down_revision = '0010_ingest_attempts'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('idempotency_records', schema=None) as batch_op:
        batch_op.add_column(sa.Column('pending', sa.Boolean(), server_default=sa.false(), nullable=False))


def downgrade() -> None:
    with op.batch_alter_table('idempotency_records', schema=None) as batch_op:
        batch_op.drop_column('pending')
