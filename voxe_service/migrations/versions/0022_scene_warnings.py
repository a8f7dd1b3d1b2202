"""A scene keeps what its ingest loaded the upload without (a mesh's warnings: an OBJ's .mtl not sent, a PLY's
TextureFile unread), shown with the scene, and told as a ``warning`` event to each job created on it once it is ready:
they had been told to the jobs waiting for its ingest alone, and said nowhere after.

Scenes ingested before the column existed: NULL (their warnings were not kept; jobs on them are told none).

Revision ID: 0022_scene_warnings
Revises: 0021_key_expiry
Create Date: 2026-12-07 16:30:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0022_scene_warnings'
down_revision = '0021_key_expiry'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.add_column(sa.Column('warnings', sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.drop_column('warnings')
