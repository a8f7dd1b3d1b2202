"""A webhook delivery records the receiver its URL goes to (``scheme://host:port``), indexed with its state and due
time: the sender caps its attempts in flight per receiver, whatever path each job's URL names, and when receivers at
their cap have the earliest due, a claim reads each receiver's earliest off that index rather than ranking every due
one. The index on the due time alone becomes one on (state, due time), off which a claim reads the earliest due first
(alone, PostgreSQL had scanned it for a receiver's earliest, past every other receiver's due before it).

Deliveries written before the column existed get their URL's origin. The column keeps its server default (''), as
the model declares it: on SQLite, taking it off would rebuild the table (see 0009_byte_sizes).

Revision ID: 0012_webhook_origin
Revises: 0011_idempotency_pending
Create Date: 2026-12-06 10:30:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from voxe_service.webhooks import webhook_origin

revision = '0012_webhook_origin'
down_revision = '0011_idempotency_pending'
branch_labels = None
depends_on = None

BATCH = 1000


def upgrade() -> None:
    with op.batch_alter_table('webhook_deliveries', schema=None) as batch_op:
        batch_op.add_column(sa.Column('origin', sa.Text(), server_default='', nullable=False))
    conn, last = op.get_bind(), ''
    while rows := conn.execute(sa.text('SELECT id, url FROM webhook_deliveries WHERE id > :last ORDER BY id LIMIT '
                                       f'{BATCH}'), {'last': last}).all():  # (a batch at a time in memory)
        conn.execute(sa.text('UPDATE webhook_deliveries SET origin = :origin WHERE id = :id'),
                     [{'id': row.id, 'origin': webhook_origin(row.url)} for row in rows])
        last = rows[-1].id
    op.create_index('ix_webhook_deliveries_state_origin_due', 'webhook_deliveries',
                    ['state', 'origin', 'next_attempt_at'], unique=False)
    op.create_index('ix_webhook_deliveries_state_due', 'webhook_deliveries', ['state', 'next_attempt_at'], unique=False)
    op.drop_index('ix_webhook_deliveries_next_attempt_at', table_name='webhook_deliveries')


def downgrade() -> None:
    op.create_index('ix_webhook_deliveries_next_attempt_at', 'webhook_deliveries', ['next_attempt_at'], unique=False)
    op.drop_index('ix_webhook_deliveries_state_due', table_name='webhook_deliveries')
    op.drop_index('ix_webhook_deliveries_state_origin_due', table_name='webhook_deliveries')
    with op.batch_alter_table('webhook_deliveries', schema=None) as batch_op:
        batch_op.drop_column('origin')
