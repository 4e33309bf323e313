"""Alembic environment: migrations run on the connection :func:`service.db.migrate.upgrade` passes in
``config.attributes["connection"]`` (the store's own engine, so SQLite in memory works too)."""

from alembic import context

from service.db.rows import Base

connection = context.config.attributes["connection"]
# batch mode: SQLite alters a table by copying it, which later revisions will need
context.configure(connection=connection, target_metadata=Base.metadata, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
