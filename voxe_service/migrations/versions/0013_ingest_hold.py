"""A scene records the one run of its ingest that holds it (token and lease), as a job records its stage's: two
workers never ingest one scene at once, and the reaper sends again the ingest of a scene whose worker died

Scenes written before the columns existed: no run holds them (NULL).

Revision ID: 0013_ingest_hold
Revises: 0012_webhook_origin
Create Date: 2026-12-06 13:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0013_ingest_hold'
down_revision = '0012_webhook_origin'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.add_column(sa.Column('ingest_token', sa.String(length=32), nullable=True))
        batch_op.add_column(sa.Column('ingest_lease_until', sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.drop_column('ingest_lease_until')
        batch_op.drop_column('ingest_token')
