"""API keys, owners of scenes and jobs, idempotency records

Existing scenes and jobs are given to the built-in ``local`` key (the one requests act as while
authentication is off), so nothing uploaded before keys existed becomes visible to a real key.

Revision ID: 0002_access
Revises: 0001
Create Date: 2026-12-01 14:50:00
"""

from __future__ import annotations

from datetime import datetime, timezone

import sqlalchemy as sa
from alembic import op

revision = '0002_access'
down_revision = '0001'
branch_labels = None
depends_on = None

LOCAL_KEY_ID = 'local'


def upgrade() -> None:
    api_keys = op.create_table('api_keys',
    sa.Column('id', sa.String(length=32), nullable=False),
    sa.Column('name', sa.String(length=255), nullable=False),
    sa.Column('token_sha256', sa.String(length=64), nullable=True),
    sa.Column('max_active_jobs', sa.Integer(), nullable=True),
    sa.Column('max_upload_bytes', sa.BigInteger(), nullable=True),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('revoked_at', sa.DateTime(timezone=True), nullable=True),
    sa.PrimaryKeyConstraint('id')
    )
    op.bulk_insert(api_keys, [{'id': LOCAL_KEY_ID, 'name': 'local (authentication off, loopback only)',
                               'token_sha256': None, 'created_at': datetime.now(timezone.utc)}])
    op.create_table('idempotency_records',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('owner_key_id', sa.String(length=32), nullable=False),
    sa.Column('endpoint', sa.String(length=32), nullable=False),
    sa.Column('idempotency_key', sa.String(length=255), nullable=False),
    sa.Column('request_sha256', sa.String(length=64), nullable=False),
    sa.Column('resource_id', sa.String(length=32), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['owner_key_id'], ['api_keys.id'], ),
    sa.PrimaryKeyConstraint('id'),
    sa.UniqueConstraint('owner_key_id', 'endpoint', 'idempotency_key', name='uq_idempotency')
    )
    for table in ('scenes', 'jobs'):
        # Existing rows belong to the local key; the default is dropped once they have it.
        with op.batch_alter_table(table, schema=None) as batch_op:
            batch_op.add_column(sa.Column('owner_key_id', sa.String(length=32), nullable=False,
                                          server_default=LOCAL_KEY_ID))
        with op.batch_alter_table(table, schema=None) as batch_op:
            batch_op.alter_column('owner_key_id', server_default=None)
            batch_op.create_index(batch_op.f(f'ix_{table}_owner_key_id'), ['owner_key_id'], unique=False)
            batch_op.create_foreign_key(f'fk_{table}_owner_key_id', 'api_keys', ['owner_key_id'], ['id'])


def downgrade() -> None:
    for table in ('jobs', 'scenes'):
        with op.batch_alter_table(table, schema=None) as batch_op:
            batch_op.drop_constraint(f'fk_{table}_owner_key_id', type_='foreignkey')
            batch_op.drop_index(batch_op.f(f'ix_{table}_owner_key_id'))
            batch_op.drop_column('owner_key_id')
    op.drop_table('idempotency_records')
    op.drop_table('api_keys')
