"""Indexes that only repeat the lead of another index or of a unique constraint are dropped: the lookups by their
column are served as well by the longer one (its index, on SQLite and PostgreSQL alike), and each insert kept one
index fewer up to date.

- scenes and jobs, owner_key_id: the listing's index on (owner_key_id, created_at, id) of 0014 serves every lookup
  by owner (the listings and their counts, the active-job and stored-byte quotas, and PostgreSQL's check of an
  api_keys row's deletion against its referencing rows).
- artifacts, job_id (uq_artifact_job_name: job_id, name), webhook_deliveries, job_id (uq_webhook_delivery_event:
  job_id, event_id) and reconstructions, scene_id (uq_reconstruction_scene_params: scene_id, params_key): the unique
  constraint's index serves a job's or scene's rows, their ON DELETE CASCADE from jobs or scenes included.

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

# (index, table, column): each the lead of another index or unique constraint of its table
LEADING_INDEXES = (
    ('ix_jobs_owner_key_id', 'jobs', 'owner_key_id'),
    ('ix_scenes_owner_key_id', 'scenes', 'owner_key_id'),
    ('ix_artifacts_job_id', 'artifacts', 'job_id'),
    ('ix_webhook_deliveries_job_id', 'webhook_deliveries', 'job_id'),
    ('ix_reconstructions_scene_id', 'reconstructions', 'scene_id'),
)


def upgrade() -> None:
    for name, table, _ in LEADING_INDEXES:
        op.drop_index(name, table_name=table)


def downgrade() -> None:
    for name, table, column in reversed(LEADING_INDEXES):
        op.create_index(name, table, [column], unique=False)
