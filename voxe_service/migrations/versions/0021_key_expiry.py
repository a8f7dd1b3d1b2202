"""An API key may expire: ``expires_at``, set by ``python -m api.admin create-key --expires-in`` (or ``update-key``);
from then on its token is refused with a 401 saying it expired. Keys had been valid until revoked, however long ago
they were handed out.

Keys written before the column existed: NULL, they never expire (as before).

Revision ID: 0021_key_expiry
Revises: 0020_job_storage_outages
Create Date: 2026-12-07 13:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0021_key_expiry'
down_revision = '0020_job_storage_outages'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('api_keys', schema=None) as batch_op:
        batch_op.add_column(sa.Column('expires_at', sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('api_keys', schema=None) as batch_op:
        batch_op.drop_column('expires_at')
