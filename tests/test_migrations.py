"""Schema migrations of the scene store (service.db.migrate), on SQLite and on the real PostgreSQL at
127.0.0.1:5432 (a throw-away database per test): an empty database migrates to the newest
revision with exactly the schema the models describe; a database made by the release before
migrations (the baseline's tables, no ``alembic_version``) keeps its rows and is brought
under migrations; a database already at the newest revision is left alone."""

from __future__ import annotations

from collections.abc import Iterator
from importlib import import_module

import pytest
from helpers import throwaway_postgres
from sqlalchemy import create_engine, inspect, text

from service.db.migrate import BASELINE, current, head, upgrade
from service.db.rows import Base
from service.db.scenes import SceneStore


@pytest.fixture(params=["sqlite", "postgresql"])
def url(request, tmp_path) -> Iterator[str]:
    """The URL of an empty database."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'cmc.db'}"
        return
    with throwaway_postgres() as url:
        yield url


def schema(engine, name: str | None = None) -> dict:
    """Tables of database schema ``name`` -> (columns with type and nullability, indexes, unique
    constraints), comparable across databases."""
    insp = inspect(engine)
    out = {}
    for table in sorted(set(insp.get_table_names(name)) - {"alembic_version"}):
        columns = {c["name"]: (str(c["type"]), c["nullable"]) for c in insp.get_columns(table, name)}
        indexes = {(i["name"], tuple(i["column_names"]), bool(i["unique"])) for i in insp.get_indexes(table, name)}
        uniques = {(u["name"], tuple(u["column_names"])) for u in insp.get_unique_constraints(table, name)}
        out[table] = (columns, indexes, uniques)
    return out


def test_an_empty_database_migrates_to_the_models_schema(url: str) -> None:
    migrated = create_engine(url)
    upgrade(migrated)
    assert current(migrated) == head()
    if url.startswith("sqlite"):  # the models' tables in a database beside it
        reference, name = create_engine(url.replace("cmc.db", "reference.db")), None
    else:  # in a schema of its own
        with migrated.begin() as conn:
            conn.execute(text("CREATE SCHEMA reference"))
        reference, name = (
            create_engine(url, execution_options={"schema_translate_map": {None: "reference"}}),
            "reference",
        )
    Base.metadata.create_all(reference)
    want = schema(reference if name is None else migrated, name)
    got = schema(migrated)
    reference.dispose()
    migrated.dispose()
    assert got == want, "the migrations and the models (service/db/rows.py) describe different schemas"


@pytest.mark.parametrize("stamped", [False, True])
def test_a_database_of_the_previous_release_migrates_and_keeps_its_rows(url: str, stamped: bool) -> None:
    """The previous release made the baseline's tables on start (``create_all``, no version
    table); stamped at the baseline or not, it migrates to the newest revision and its scenes
    survive."""
    engine = create_engine(url)
    import_module("service.db.migrations.versions.0001_baseline").META.create_all(engine)
    if stamped:
        with engine.begin() as conn:
            conn.execute(text("CREATE TABLE alembic_version (version_num VARCHAR(32) NOT NULL PRIMARY KEY)"))
            conn.execute(text(f"INSERT INTO alembic_version VALUES ('{BASELINE}')"))
    engine.dispose()
    old = SceneStore(url, migrate=False)
    rec, _ = old.create("o", {"preset": "fast"}, ["a.jpg", "b.jpg"], ["00.jpg", "01.jpg"], False, None, None)
    old.close()
    store = SceneStore(url)  # migrates on open
    assert current(store.engine) == head()
    assert store.get(rec.id, "o") is not None
    store.close()


def test_an_old_scenes_table_gets_its_missing_columns(url: str) -> None:
    """A database from before the outbox (no ``send_at``) is completed by the baseline revision."""
    engine = create_engine(url)
    import_module("service.db.migrations.versions.0001_baseline").META.create_all(engine)
    with engine.begin() as conn:
        conn.execute(text("DROP INDEX ix_scenes_send_at"))
        conn.execute(text("ALTER TABLE scenes DROP COLUMN send_at"))
    upgrade(engine)
    assert "send_at" in {c["name"] for c in inspect(engine).get_columns("scenes")}
    assert "ix_scenes_send_at" in {i["name"] for i in inspect(engine).get_indexes("scenes")}
    upgrade(engine)  # at head: nothing to do
    assert current(engine) == head()
    engine.dispose()


def test_processes_starting_together_migrate_one_at_a_time(url: str) -> None:
    """On PostgreSQL an advisory lock serialises migrations (the API and workers may start at once)."""
    if not url.startswith("postgresql"):
        pytest.skip("SQLite is one process's database (cmc serve)")
    from concurrent.futures import ThreadPoolExecutor

    engines = [create_engine(url) for _ in range(4)]
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(upgrade, engines))
    assert {current(e) for e in engines} == {head()}
    for e in engines:
        e.dispose()
