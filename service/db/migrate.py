"""Schema migrations of the scene store (Alembic; revisions in service/db/migrations/versions/).

:func:`upgrade` brings a database to the newest revision: an empty one is created, one made
before migrations existed is completed by the baseline revision. The store runs it on open when
``CMC_MIGRATE_ON_START`` is true (the default: embedded mode, tests); the deployment turns that
off and runs ``python -m service.db.migrate`` once, as the compose service ``migrate``, before the
API and the workers start.
"""

from __future__ import annotations

from importlib import import_module
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import text

from service.db.engine import open_engine
from service.db.rows import Base

MIGRATIONS = Path(__file__).resolve().parent / "migrations"
BASELINE = "0001"  # the schema of the first release with migrations
LOCK_KEY = 0x434D43  # PostgreSQL advisory lock held while migrating ("CMC")


def _config(connection: Any) -> Config:
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.attributes["connection"] = connection
    return cfg


def head() -> str:
    """The newest revision."""
    return ScriptDirectory.from_config(_config(None)).get_current_head() or ""


def current(engine: Any) -> str | None:
    """The revision the database is at; None: not under migrations (empty, or made before)."""
    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def upgrade(engine: Any) -> None:
    """Migrate the database of SQLAlchemy ``engine`` to the newest revision (no-op when it is).
    First the baseline's tables and columns that the models still use are completed (``complete``
    of revision 0001): a database made before migrations may lack a column its release had not
    added yet, whether or not it was stamped since."""
    with engine.begin() as conn:
        if conn.dialect.name == "postgresql":  # processes starting together migrate one at a time
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": LOCK_KEY})
        import_module("service.db.migrations.versions.0001_baseline").complete(conn, Base.metadata)
        command.upgrade(_config(conn), "head")


def main() -> None:
    from service.settings import load_settings

    engine = open_engine(load_settings().resolved_database_url)
    upgrade(engine)
    print(f"scene store at revision {current(engine)} (head {head()})")
    engine.dispose()


if __name__ == "__main__":
    main()
