"""The single-column owner_key_id indexes of scenes and jobs are dropped: the listing's index on (owner_key_id,
created_at, id) of 0014 begins with that column, so it serves every lookup by owner (the listings and their counts,
the active-job and stored-byte quotas, and PostgreSQL's check of an api_keys row's deletion against its referencing
rows) as well, and each insert kept one index fewer up to date.

Revision ID: 0015_owner_index_prefix
Revises: 0014_listing_order
Create Date: 2026-12-06 15:10:00
"""

from __future__ import annotations

from alembic import op

revision = '0015_owner_index_prefix'
down_revision = '0014_listing_order'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.drop_index('ix_jobs_owner_key_id', table_name='jobs')
    op.drop_index('ix_scenes_owner_key_id', table_name='scenes')


def downgrade() -> None:
    op.create_index('ix_scenes_owner_key_id', 'scenes', ['owner_key_id'], unique=False)
    op.create_index('ix_jobs_owner_key_id', 'jobs', ['owner_key_id'], unique=False)
