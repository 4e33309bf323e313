"""Baseline: the scene store's schema as the first release with migrations left it.

Tables ``scenes``, ``scene_callbacks`` and ``webhook_deliveries``. Also completes a database made
before migrations existed (no ``alembic_version``): a missing table is created, and a ``scenes``
table from an older release gets the (nullable) columns and indexes it lacks, as the store did on
start until then. Frozen: later schema changes are new revisions, never edits of this one.

Revision ID: 0001
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

META = sa.MetaData()
sa.Table(
    "scenes",
    META,
    sa.Column("id", sa.String(32), primary_key=True),
    sa.Column("owner", sa.String(64), nullable=False, index=True),
    sa.Column("status", sa.String(20), nullable=False, index=True),
    sa.Column("phase", sa.String(10), nullable=False),
    sa.Column("progress", sa.Float, nullable=False),
    sa.Column("eta_seconds", sa.Float, nullable=True),
    sa.Column("detail", sa.String(200), nullable=True),
    sa.Column("error_code", sa.String(40), nullable=True),
    sa.Column("error_message", sa.String(2000), nullable=True),
    sa.Column("options", sa.JSON, nullable=False),
    sa.Column("upload_names", sa.JSON, nullable=False),
    sa.Column("upload_files", sa.JSON, nullable=False),
    sa.Column("has_cameras", sa.Boolean, nullable=False),
    sa.Column("idempotency_key", sa.String(200), nullable=True),
    sa.Column("request_digest", sa.String(64), nullable=True),
    sa.Column("attempts", sa.Integer, nullable=False),
    sa.Column("lease_owner", sa.String(100), nullable=True),
    sa.Column("lease_expires_at", sa.Float, nullable=True),
    sa.Column("cancel_requested", sa.Boolean, nullable=False),
    sa.Column("deleted", sa.Boolean, nullable=False, index=True),
    sa.Column("stats", sa.JSON, nullable=False),
    sa.Column("created_at", sa.Float, nullable=False),
    sa.Column("updated_at", sa.Float, nullable=False),
    sa.Column("enqueued_at", sa.Float, nullable=True),
    sa.Column("started_at", sa.Float, nullable=True),
    sa.Column("finished_at", sa.Float, nullable=True),
    sa.Column("send_at", sa.Float, nullable=True, index=True),
    sa.UniqueConstraint("owner", "idempotency_key", name="uq_scene_idempotency"),
)
sa.Table(
    "scene_callbacks",
    META,
    sa.Column("scene_id", sa.String(32), primary_key=True),
    sa.Column("url", sa.String(2000), nullable=False),
)
sa.Table(
    "webhook_deliveries",
    META,
    sa.Column("id", sa.String(32), primary_key=True),
    sa.Column("scene_id", sa.String(32), nullable=False, index=True),
    sa.Column("owner", sa.String(64), nullable=False),
    sa.Column("event", sa.String(40), nullable=False),
    sa.Column("url", sa.String(2000), nullable=False),
    sa.Column("body", sa.Text, nullable=False),
    sa.Column("status", sa.String(10), nullable=False, index=True),
    sa.Column("attempts", sa.JSON, nullable=False),
    sa.Column("next_attempt_at", sa.Float, nullable=True, index=True),
    sa.Column("created_at", sa.Float, nullable=False),
    sa.Column("updated_at", sa.Float, nullable=False),
    sa.Column("delivered_at", sa.Float, nullable=True),
)


def upgrade() -> None:
    complete(op.get_bind())


def complete(bind: sa.Connection, models: sa.MetaData | None = None) -> None:
    """Create the missing tables of this revision and add the missing columns (with their
    indexes) of existing ones; with ``models``, only the tables and columns they still have.
    Idempotent; :func:`service.db.migrate.upgrade` runs it before every upgrade, for a database an
    older release made that was stamped by hand or lost a column."""
    inspector = sa.inspect(bind)
    for table in META.sorted_tables:
        if models is not None and table.name not in models.tables:
            continue
        if not inspector.has_table(table.name):
            table.create(bind)
            continue
        have = {c["name"] for c in inspector.get_columns(table.name)}
        wanted = models.tables[table.name].c if models is not None else table.c
        for column in table.columns:  # an older release's table: only nullable columns were added
            if column.name not in have and column.name in wanted:
                kind = column.type.compile(dialect=bind.dialect)
                bind.execute(sa.text(f'ALTER TABLE {table.name} ADD COLUMN "{column.name}" {kind}'))
                for index in table.indexes:
                    if [c.name for c in index.columns] == [column.name]:
                        index.create(bind, checkfirst=True)


def downgrade() -> None:
    for table in reversed(META.sorted_tables):
        op.drop_table(table.name)
