"""The scene store on SQLite and on the real PostgreSQL at 127.0.0.1:5432 (a throw-away database
per test): job claims are exclusive, leases expire and are re-queued, idempotent creates, the
tombstones of deleted scenes, pagination."""

from __future__ import annotations

import time

import pytest
from helpers import finished_job, throwaway_postgres

from service.db.rows import IdempotencyConflict
from service.db.scenes import SceneStore


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request, tmp_path):
    if request.param == "sqlite":
        s = SceneStore(f"sqlite:///{tmp_path / 'cmc.db'}")
        yield s
        s.close()
        return
    with throwaway_postgres() as url:
        s = SceneStore(url)
        try:
            yield s
        finally:
            s.close()


def make(store: SceneStore, owner: str = "o", key: str | None = None, digest: str | None = None):
    rec, created = store.create(owner, {"preset": "fast"}, ["a.jpg", "b.jpg"], ["00.jpg", "01.jpg"], False, key, digest)
    return rec, created


def test_claim_is_exclusive_and_follows_the_phase(store: SceneStore) -> None:
    rec, _ = make(store)
    assert store.claim(rec.id, "train", "w1", 30) is None  # wrong phase
    got = store.claim(rec.id, "poses", "w1", 30)
    assert got is not None and got.lease_owner == "w1" and got.started_at is not None
    assert store.claim(rec.id, "poses", "w2", 30) is None  # held by a live worker
    assert store.heartbeat(rec.id, "w2", 30, progress=0.5).holds_lease is False
    hb = store.heartbeat(rec.id, "w1", 30, status="estimating_poses", progress=0.5)
    assert hb.holds_lease and not hb.cancel_requested
    assert store.get(rec.id).progress == 0.5
    assert not store.advance(rec.id, "w2", "train", "training")
    assert store.advance(rec.id, "w1", "train", "training", progress=0.0)
    after = store.get(rec.id)
    assert (after.phase, after.status, after.lease_owner) == ("train", "training", None)
    assert store.claim(rec.id, "poses", "w1", 30) is None  # a duplicate of the finished phase
    assert store.claim(rec.id, "train", "w2", 30) is not None


def test_expired_lease_is_requeued_then_failed_after_max_attempts(store: SceneStore) -> None:
    rec, _ = make(store)
    assert store.stale_jobs(3600) == []
    for attempt in (1, 2):
        assert store.claim(rec.id, "poses", f"w{attempt}", 0.05) is not None
        time.sleep(0.1)
        stale = store.stale_jobs(3600)
        assert [s.id for s in stale] == [rec.id]
        assert store.requeue(stale[0], max_attempts=3) is True
        assert store.requeue(stale[0], max_attempts=3) is False  # already handled by someone else
        assert store.get(rec.id).attempts == attempt
    assert store.claim(rec.id, "poses", "w3", 0.05) is not None
    time.sleep(0.1)
    assert store.requeue(store.stale_jobs(3600)[0], max_attempts=3) is False
    failed = store.get(rec.id)
    assert failed.status == "failed" and failed.error_code == "worker_lost" and failed.finished_at is not None


def test_a_queued_job_whose_message_was_lost_is_sent_again(store: SceneStore) -> None:
    rec, _ = make(store)
    assert store.stale_jobs(requeue_after_seconds=60) == []
    time.sleep(0.05)
    assert [s.id for s in store.stale_jobs(requeue_after_seconds=0.01)] == [rec.id]
    assert store.requeue(store.stale_jobs(0.01)[0], max_attempts=1) is True  # not a lost worker
    assert store.get(rec.id).attempts == 0


def test_outbox_a_message_is_due_until_the_broker_took_it(store: SceneStore) -> None:
    """Every change that needs a message makes it due in the same statement; a sender takes it
    (one sender only), and it stays due until sent or the job is claimed."""
    rec, _ = make(store)
    assert store.due_messages() == []  # the API sends the first message itself
    store.claim(rec.id, "poses", "w1", 30)
    assert store.advance(rec.id, "w1", "train", "training", detail="waiting for a worker")
    due = store.due_messages()
    assert [(d.id, d.phase) for d in due] == [(rec.id, "train")]
    assert store.due_messages(scene_id="other") == []
    retry_at = time.time() + 30
    assert store.take_message(due[0], retry_at) is True
    assert store.take_message(due[0], retry_at + 1) is False  # another sender took it first
    assert store.due_messages() == []  # taken: due again at retry_at unless sent
    store.message_failed(rec.id, detail="queue down")
    assert store.get(rec.id).detail == "queue down" and store.get(rec.id).send_at == retry_at
    store.message_sent(rec.id, retry_at, detail="waiting for a worker")
    after = store.get(rec.id)
    assert after.send_at is None and after.detail == "waiting for a worker"
    # a worker stopping for shutdown hands the job on; claiming it clears the message
    store.claim(rec.id, "train", "w2", 30)
    store.heartbeat(rec.id, "w2", 30, detail="training")
    store.message_failed(rec.id, detail="queue down")  # never over a running job's detail
    assert store.get(rec.id).detail == "training"
    store.release(rec.id, "w2", resend=True, detail="waiting for a worker")
    assert [d.id for d in store.due_messages()] == [rec.id]
    assert store.claim(rec.id, "train", "w3", 0.05) is not None and store.due_messages() == []
    time.sleep(0.1)  # w3 died: the reaper's re-queue makes it due again
    assert store.requeue(store.stale_jobs(3600)[0], max_attempts=3, detail="waiting for a worker")
    assert [d.id for d in store.due_messages()] == [rec.id]
    store.delete(rec.id)
    assert store.due_messages() == []  # nothing is sent for a cancelled job


def test_an_older_database_gets_the_new_columns(store: SceneStore) -> None:
    """A database made before a column existed (here: the outbox's send_at) opens with it added
    and its rows kept."""
    from sqlalchemy import inspect, text

    rec, _ = make(store)
    with store.engine.begin() as conn:
        conn.execute(text("DROP INDEX ix_scenes_send_at"))
        conn.execute(text("ALTER TABLE scenes DROP COLUMN send_at"))
    url = store.engine.url.render_as_string(hide_password=False)
    store.close()
    reopened = SceneStore(url)
    try:
        assert "send_at" in {c["name"] for c in inspect(reopened.engine).get_columns("scenes")}
        assert "ix_scenes_send_at" in {i["name"] for i in inspect(reopened.engine).get_indexes("scenes")}
        assert reopened.get(rec.id).send_at is None and reopened.get(rec.id).owner == "o"
        reopened.claim(rec.id, "poses", "w1", 30)
        assert reopened.advance(rec.id, "w1", "train", "training")
        assert [d.id for d in reopened.due_messages()] == [rec.id]
    finally:
        reopened.close()


def test_delete_leaves_a_tombstone_that_stops_the_worker(store: SceneStore) -> None:
    rec, _ = make(store)
    store.claim(rec.id, "poses", "w1", 30)
    store.delete(rec.id)
    assert store.get(rec.id) is None
    tomb = store.get(rec.id, include_deleted=True)
    assert tomb.deleted and tomb.status == "cancelled" and tomb.cancel_requested
    hb = store.heartbeat(rec.id, "w1", 30)
    assert hb.cancel_requested and not hb.holds_lease  # cancelled is terminal: the lease is void
    assert store.stale_jobs(0) == [] and store.unfinished_jobs() == []


def test_idempotent_create(store: SceneStore) -> None:
    first, created = make(store, key="k1", digest="d1")
    again, created_again = make(store, key="k1", digest="d1")
    assert created and not created_again and again.id == first.id
    with pytest.raises(IdempotencyConflict):
        make(store, key="k1", digest="d2")
    other_owner, created = make(store, owner="p", key="k1", digest="d1")
    assert created and other_owner.id != first.id
    unkeyed = [make(store)[0].id for _ in range(2)]
    assert len(set(unkeyed)) == 2


def test_list_pages_by_owner_newest_first(store: SceneStore) -> None:
    ids = [make(store)[0].id for _ in range(5)]
    make(store, owner="someone else")
    page1 = store.list("o", 3)
    page2 = store.list("o", 3, (page1[-1].created_at, page1[-1].id))
    assert [r.id for r in page1 + page2] == ids[::-1]
    assert store.count_by_status()["queued"] == 6


def test_fail_and_finished_durations(store: SceneStore) -> None:
    rec, _ = make(store)
    store.fail(rec.id, "training_failed", "x" * 5000)
    done = store.get(rec.id)
    assert done.status == "failed" and len(done.error_message) == 2000
    store.fail(rec.id, "other", "ignored")  # already ended
    assert store.get(rec.id).error_code == "training_failed"
    assert [s for s, _ in store.finished_durations()] == ["failed"]


def test_sqlite_store_creates_its_folder(tmp_path) -> None:
    s = SceneStore(f"sqlite:///{tmp_path / 'fresh' / 'data' / 'cmc.db'}")
    make(s)
    assert (tmp_path / "fresh" / "data" / "cmc.db").exists()
    s.close()


def test_latest_ready_lists_ready_jobs_latest_first(store: SceneStore) -> None:
    first = finished_job(store, {"preset": "fast"}, {"n": 1})
    failed, _ = make(store)
    store.fail(failed.id, "training_failed", "diverged")
    second = finished_job(store, {"preset": "fast"}, {"n": 2})
    make(store)  # still queued
    store.delete(first)  # a deleted scene's measurements still count
    assert [(r.id, r.stats) for r in store.latest_ready(5)] == [(second, {"n": 2}), (first, {"n": 1})]
    assert [r.id for r in store.latest_ready(1)] == [second]
