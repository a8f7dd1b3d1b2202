"""The job and scene listings' order, newest first (created_at, then id), is read off an index on (owner_key_id,
created_at, id): a page after a cursor seeks to its place (api/paging.py), where a key's every row had been read and
sorted for each page.

Revision ID: 0014_listing_order
Revises: 0013_ingest_hold
Create Date: 2026-12-06 13:30:00
"""

from __future__ import annotations

from alembic import op

revision = '0014_listing_order'
down_revision = '0013_ingest_hold'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index('ix_jobs_owner_created', 'jobs', ['owner_key_id', 'created_at', 'id'], unique=False)
    op.create_index('ix_scenes_owner_created', 'scenes', ['owner_key_id', 'created_at', 'id'], unique=False)


def downgrade() -> None:
    op.drop_index('ix_scenes_owner_created', table_name='scenes')
    op.drop_index('ix_jobs_owner_created', table_name='jobs')
