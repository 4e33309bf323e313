"""Video builds as jobs (service.db.videos): one record per scene and path with a lease, progress,
error and cancel, like scene jobs; the reaper sends a build again whose worker went silent."""

from __future__ import annotations

import time

from service.db.scenes import SceneStore


def _store(tmp_path) -> tuple[SceneStore, str]:
    store = SceneStore(f"sqlite:///{tmp_path / 'cmc.db'}")
    rec, _ = store.create("o", {"preset": "fast"}, ["a.jpg", "b.jpg"], ["00.jpg", "01.jpg"], False, None, None)
    return store, rec.id


def test_a_build_is_requested_once_claimed_by_one_worker_and_finished(tmp_path) -> None:
    store, sid = _store(tmp_path)
    videos = store.videos
    job, started = videos.request(sid, "orbit")
    assert started and job.status == "building" and job.progress == 0
    assert videos.request(sid, "orbit") == (job, False)  # asking again sends nothing
    assert videos.claim(sid, "orbit", "w1", 30) and not videos.claim(sid, "orbit", "w2", 30)
    hb = videos.heartbeat(sid, "orbit", "w1", 30, 0.5)
    assert hb.holds_lease and not hb.cancel_requested and videos.get(sid, "orbit").progress == 0.5
    assert not videos.finish(sid, "orbit", "w2")  # only the holder ends it
    assert videos.finish(sid, "orbit", "w1") and videos.get(sid, "orbit").status == "ready"
    store.close()


def test_failure_is_kept_until_seen_then_retried(tmp_path) -> None:
    store, sid = _store(tmp_path)
    videos = store.videos
    videos.request(sid, "spiral")
    videos.claim(sid, "spiral", "w1", 30)
    assert videos.finish(sid, "spiral", "w1", error="ValueError: boom")
    failed = videos.get(sid, "spiral")
    assert failed.status == "failed" and failed.error == "ValueError: boom"
    videos.forget(sid, "spiral")
    assert videos.request(sid, "spiral")[1]  # a new build
    store.close()


def test_deleting_the_scene_cancels_its_builds(tmp_path) -> None:
    store, sid = _store(tmp_path)
    videos = store.videos
    videos.request(sid, "dolly")
    videos.claim(sid, "dolly", "w1", 30)
    store.delete(sid)
    hb = videos.heartbeat(sid, "dolly", "w1", 30, 0.2)
    assert hb.cancel_requested and not hb.holds_lease
    assert videos.get(sid, "dolly").status == "cancelled" and videos.unfinished() == []
    store.close()


def test_a_silent_worker_s_build_is_sent_again_then_failed(tmp_path) -> None:
    store, sid = _store(tmp_path)
    videos = store.videos
    videos.request(sid, "orbit")
    assert videos.claim(sid, "orbit", "w1", 0.05)
    time.sleep(0.1)  # w1 died
    (stale,) = videos.stale(3600)
    assert videos.requeue(stale, max_attempts=1) and videos.claim(sid, "orbit", "w2", 0.05)
    time.sleep(0.1)
    (stale,) = videos.stale(3600)
    assert not videos.requeue(stale, max_attempts=1)
    assert videos.get(sid, "orbit").status == "failed"
    store.close()
