"""PLY artifacts recorded before the worker named their type (application/octet-stream) get model/ply, the type it
records for them now, so a download's Content-Type does not depend on when its job ran. Downgrading gives them back
the type the earlier worker recorded.

It retypes the rows there are when it runs, once: a PLY that a worker still running the earlier code publishes after
it (the window of a rolling upgrade: the API migrates at startup, so restarting it before the workers opens one)
keeps application/octet-stream, in its listing and its download, and no later revision retypes it. Restart the
workers first to leave none; to retype those left once every worker is new, run RETYPE_TO_PLY's statement (below)
by hand: it changes nothing else and may run any number of times. (Not a downgrade and upgrade: a downgrade to
0015 also undoes every later revision, 0017's scenes.lost_ingest_resends among them, which the running service
reads.)

Revision ID: 0016_ply_content_type
Revises: 0015_owner_index_prefix
Create Date: 2026-12-06 18:45:00
"""

from __future__ import annotations

from alembic import op

revision = '0016_ply_content_type'
down_revision = '0015_owner_index_prefix'
branch_labels = None
depends_on = None


RETYPE_TO_PLY = ("UPDATE artifacts SET content_type = 'model/ply' "
                 "WHERE content_type = 'application/octet-stream' AND lower(name) LIKE '%.ply'")


def upgrade() -> None:
    op.execute(RETYPE_TO_PLY)


def downgrade() -> None:
    op.execute("UPDATE artifacts SET content_type = 'application/octet-stream' "
               "WHERE content_type = 'model/ply' AND lower(name) LIKE '%.ply'")
