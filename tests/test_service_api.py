"""The REST API through FastAPI's TestClient, in embedded mode (the real pipeline in a thread).

One tiny synthetic scene (known poses and depths) is reconstructed once per module and checked
against its exact ground truth; upload limits, auth, idempotency, pagination and errors use a
queue that only records what was sent, so they train nothing.
"""

from __future__ import annotations

import io
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx2
import numpy as np
import pytest
import uvicorn
from fastapi.testclient import TestClient
from helpers import REDIS_URL, finished_job, render_body, synthetic_upload
from PIL import Image

from cmc.data.datasets import DEFAULT_LAYERS, render_layers
from cmc.eval.metrics import psnr
from cmc.geometry.camera_paths import camera_path, capture_radius, mean_pose, orbit_path
from cmc.geometry.cameras import Cameras, convert_pose
from cmc.serving.baking import PREVIEW_TEXEL_SCALE, BakedScene
from cmc.serving.video import path_cameras
from service.app import create_app
from service.auth import key_digest
from service.limits import MemoryLimiter, RedisLimiter
from service.negotiation import negotiate
from service.quotas import RECORD_HOLD_S
from service.schemas import RenderCamera
from service.settings import Settings, load_settings


class RecordingQueue:
    """A job queue that records submissions and runs nothing."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, str]] = []

    def submit(self, scene_id: str, phase: str) -> None:
        self.sent.append((scene_id, phase))

    def depth(self) -> dict[str, int]:
        return {"recorded": len(self.sent)}

    def submit_video(self, scene_id: str, path: str) -> None:
        self.sent.append((scene_id, f"video {path}"))

    def ping(self) -> None:
        pass


def settings_for(tmp: Path, **overrides):
    base = dict(data_dir=tmp, mode="embedded", api_keys="", api_keys_file=None, heartbeat_seconds=0.2)
    base["allowed_hosts"] = "testserver"  # the Host of TestClient's requests (open mode accepts only local ones)
    return load_settings(**{**base, **overrides})


def wait_for(client: TestClient, scene_id: str, statuses: tuple[str, ...], timeout: float = 240, **headers) -> dict:
    t0 = time.time()
    while time.time() - t0 < timeout:
        body = client.get(f"/v1/scenes/{scene_id}", headers=headers).json()
        if body.get("status") in statuses:
            return body
        time.sleep(0.2)
    raise AssertionError(f"scene {scene_id} not {statuses} after {timeout} s: {body}")


@contextmanager
def live_server(app) -> Iterator[int]:
    """``app`` served by uvicorn on a free localhost port (yielded), in a thread of this process."""
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    t0 = time.time()
    while not server.started:
        assert thread.is_alive() and time.time() - t0 < 30, "uvicorn did not start"
        time.sleep(0.02)
    try:
        yield server.servers[0].sockets[0].getsockname()[1]
    finally:
        server.should_exit = True
        thread.join(10)


def raw_exchange(port: int, head: str, body_chunks: list[bytes], timeout: float = 3.0) -> tuple[int, dict, float]:
    """Send a request head and some body bytes on a socket, never the rest, and read the answer:
    (status, JSON body, seconds to answer). Fails when the server waits for the rest instead."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        t0 = time.perf_counter()
        sock.sendall(head.replace("\n", "\r\n").encode() + b"\r\n")
        for chunk in body_chunks:
            sock.sendall(chunk)
        data = b""
        while b"\r\n\r\n" not in data or len(data.split(b"\r\n\r\n", 1)[1]) < _length(data):
            more = sock.recv(65536)
            if not more:
                break
            data += more
        elapsed = time.perf_counter() - t0
    head_bytes, _, payload = data.partition(b"\r\n\r\n")
    return int(head_bytes.split()[1]), json.loads(payload), elapsed


def _length(data: bytes) -> int:
    for line in data.split(b"\r\n\r\n", 1)[0].split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            return int(value)
    return 0


def png(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray((np.clip(a, 0, 1) * 255).astype(np.uint8)).save(buf, "PNG")
    return buf.getvalue()


# -- one reconstructed scene ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ready(tmp_path_factory):
    """(client, scene id, synthetic scene, novel camera) of a scene trained to ``ready``; the
    job's writes of (status, progress, eta_seconds) to its record are in ``client.job_writes``."""
    parts, scene, novel = synthetic_upload(steps=25)
    app = create_app(settings_for(tmp_path_factory.mktemp("ready")))
    store, writes, state = app.state.services.store, [], {}
    heartbeat, advance = store.heartbeat, store.advance

    def record(fields: dict) -> None:
        changed = {k: v for k, v in fields.items() if k in ("status", "progress", "eta_seconds")}
        if not changed:  # a beat that only renews the lease
            return
        state.update(changed)
        writes.append((state.get("status"), state.get("progress"), state.get("eta_seconds")))

    # only the writes the store took (a beat after the phase gave its lease back changes nothing)
    def recording_heartbeat(scene_id, worker, lease_seconds, **fields):
        beat = heartbeat(scene_id, worker, lease_seconds, **fields)
        if beat.holds_lease:
            record(fields)
        return beat

    def recording_advance(scene_id, worker, phase, status, **fields):
        done = advance(scene_id, worker, phase, status, **fields)
        if done:
            record({**fields, "status": status})
        return done

    store.heartbeat, store.advance = recording_heartbeat, recording_advance
    with TestClient(app) as client:
        client.job_writes = writes  # type: ignore[attr-defined]
        r = client.post("/v1/scenes", files=parts)
        assert r.status_code == 202, r.text
        body = wait_for(client, r.json()["id"], ("ready", "failed"))
        assert body["status"] == "ready", body
        yield client, body["id"], scene, novel


def test_status_of_a_ready_scene(ready) -> None:
    client, sid, _, _ = ready
    body = client.get(f"/v1/scenes/{sid}").json()
    assert body["progress"] == 1.0 and body["error"] is None
    assert body["images"] == ["view0.png", "view1.png", "view2.png"]
    assert body["options"] == {"preset": "fast", "steps": 25, "resolution": 96, "seed": 0}
    assert body["created_at"] <= body["started_at"] <= body["finished_at"]
    assert body["links"]["render"] == f"/v1/scenes/{sid}/render"


def test_eta_seconds_covers_the_rest_of_the_job(ready) -> None:
    """eta_seconds is the whole job's: while estimating poses it holds the training to come, in
    every later stage it is set, and the bake has an estimate of its own."""
    from cmc.config import preset_config
    from cmc.method.eta import bake_steps, input_rays_per_mpi, reference_training_s, step_s_from_build

    client, sid, _, _ = ready
    writes = client.job_writes
    assert [w[0] for w in writes][:1] == ["estimating_poses"] and writes[-1] == ("ready", 1.0, 0.0)
    assert all(eta is not None and eta >= 0 for _, _, eta in writes)
    poses = [eta for status, _, eta in writes if status == "estimating_poses"]
    # 25 steps and the bake are still to come (the ETA in tenths of a second)
    assert min(poses) >= reference_training_s(25) - 0.05
    assert any(status == "training" and 0 < p < 1 for status, p, _ in writes)
    # Once built, before a step is measured: the 25 steps and both bakes at the step time the
    # build's own pace predicts (cmc.method.eta.step_s_from_build).
    rec = client.app.state.services.store.get(sid)
    built_step_s = step_s_from_build(rec.stats["train"]["build_seconds"], 96, 72)
    fast = preset_config("fast")
    bake_cost = bake_steps(96, 72, fast.model.margin, input_rays_per_mpi(fast, 3))
    expected = (25 + bake_cost * (1 + PREVIEW_TEXEL_SCALE**2)) * built_step_s
    assert any(s == "training" and p == 0.0 and eta == pytest.approx(expected, rel=0.02) for s, p, eta in writes)
    bake = [(p, eta) for status, p, eta in writes if status == "baking"]
    preview_bake_s = rec.stats["preview"]["bake_seconds"]
    # the final bake's first estimate: the preview's measured bake at four times its texels
    first = preview_bake_s / PREVIEW_TEXEL_SCALE**2
    assert bake[0][0] == 0.0 and bake[0][1] == pytest.approx(first, abs=0.15)
    progress = [p for p, _ in bake]  # as the heartbeat wrote it (bake() reports each MPI: test_baking)
    assert progress == sorted(progress) and all(eta > 0 for _, eta in bake)
    # the last MPI's atlas is encoded after bake() reports it: the bake counts it as a fourth MPI
    assert all(p <= 3 / 4 for p in progress)


def test_a_ready_job_leaves_its_pace_for_the_next(ready, tmp_path) -> None:
    """A ready job's stats hold what its stages took (the pose phase, the build, a step, the
    bakes, a checkpoint write, each loss phase's steps), and a new job of its kind starts its
    estimate from them (worker.pipeline.JobPace; the choice among several jobs: tests/test_eta.py)."""
    from service.db.scenes import SceneStore
    from worker.pipeline import JobPace

    client, sid, _, _ = ready
    rec = client.app.state.services.store.get(sid)
    poses, train, preview = rec.stats["poses"], rec.stats["train"], rec.stats["preview"]
    assert poses["seconds"] > 0 and train["step_seconds"] > 0 and train["checkpoint_seconds"] > 0
    recon, full = train["phase_step_seconds"]  # each loss phase's mean step
    # the steps' mean within the attempt's training time
    assert 25 * train["step_seconds"] <= train["seconds_this_attempt"] + 0.5
    store = SceneStore(f"sqlite:///{tmp_path / 'pace.db'}")  # this job alone in a store
    finished_job(store, rec.options, rec.stats, rec.has_cameras)
    new, _ = store.create("o", rec.options, ["a.png"], ["00.png"], rec.has_cameras)
    expected = (poses["seconds"], train["step_seconds"], train["build_seconds"], train["bake_seconds"])
    measured = (preview["bake_seconds"], train["checkpoint_seconds"], full / recon)
    assert JobPace.of(store, new) == JobPace(*expected, *measured)
    store.close()


def test_render_and_depth_match_the_ground_truth(ready) -> None:
    client, sid, scene, novel = ready
    gt_rgb, gt_depth = render_layers(DEFAULT_LAYERS, novel)
    r = client.post(f"/v1/scenes/{sid}/render", json=render_body(novel))
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    rgb = np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB"), dtype=np.float32) / 255
    assert rgb.shape == (72, 96, 3)
    # a novel view between two inputs after 25 steps: 28.2 dB, depth error 12 % when measured
    # (untrained, from the plane-sweep start: 23.5 dB, 29 %)
    assert psnr(rgb, gt_rgb[0]) > 25.0
    # the same camera in the OpenCV convention renders the same image
    r_cv = client.post(f"/v1/scenes/{sid}/render", json=render_body(novel, "opencv"))
    assert r_cv.content == r.content

    d = client.post(f"/v1/scenes/{sid}/depth", json=render_body(novel))
    assert d.status_code == 200 and d.headers["content-type"] == "image/png"
    counts = np.asarray(Image.open(io.BytesIO(d.content)))
    assert counts.dtype == np.uint16 or counts.dtype == np.int32
    depth = counts.astype(np.float64) * float(d.headers["depth-scale"])
    rel = np.abs(depth - gt_depth[0]) / gt_depth[0]
    assert np.median(rel) < 0.18, np.median(rel)
    # float32 .npy agrees with the 16-bit PNG to its quantisation step
    n = client.post(f"/v1/scenes/{sid}/depth", json=render_body(novel), headers={"Accept": "application/x-npy"})
    assert n.headers["content-type"] == "application/x-npy"
    exact = np.load(io.BytesIO(n.content))
    assert exact.dtype == np.float32 and exact.shape == (72, 96)
    assert np.abs(exact - depth).max() <= float(d.headers["depth-scale"])
    preview = client.post(f"/v1/scenes/{sid}/depth?preview=true", json=render_body(novel))
    assert Image.open(io.BytesIO(preview.content)).mode == "RGB"


def test_coverage_marks_what_no_input_photo_saw(ready) -> None:
    """A camera moved far to the side of the inputs: ``coverage=true`` puts the pixels no input
    photo saw in the alpha channel (render PNG, 16-bit depth PNG) and as NaN in the .npy, and
    they agree with the exact mask from the scene's true depth at 97 % of the pixels."""
    client, sid, scene, novel = ready
    pose = novel.world_from_cam.copy()
    pose[:, 0, 3] += 1.2  # beyond the inputs: the left part of the view is out of every photo
    side = Cameras(novel.K, pose, novel.width, novel.height)
    _, gt_depth = render_layers(DEFAULT_LAYERS, side)
    exact = scene.cameras.coverage(side.K[0], side.world_from_cam[0], gt_depth[0])
    assert 0.1 < exact.mean() < 0.9, exact.mean()
    body = render_body(side)
    r = client.post(f"/v1/scenes/{sid}/render?coverage=true", json=body)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    rgba = np.asarray(Image.open(io.BytesIO(r.content)))
    assert rgba.shape == (72, 96, 4) and set(np.unique(rgba[..., 3])) <= {0, 255}
    assert ((rgba[..., 3] == 255) == exact).mean() > 0.97
    plain = np.asarray(Image.open(io.BytesIO(client.post(f"/v1/scenes/{sid}/render", json=body).content)))
    np.testing.assert_array_equal(rgba[..., :3], plain)  # the colours are the render's
    assert (
        client.post(f"/v1/scenes/{sid}/render?coverage=true", json=body, headers={"Accept": "image/jpeg"}).status_code
        == 406
    )
    d = client.post(f"/v1/scenes/{sid}/depth?coverage=true", json=body)
    la = np.asarray(Image.open(io.BytesIO(d.content)).convert("LA"))  # Pillow: 16-bit grey + alpha as 8 bits
    np.testing.assert_array_equal(la[..., 1] == 255, rgba[..., 3] == 255)
    n = client.post(f"/v1/scenes/{sid}/depth?coverage=true", json=body, headers={"Accept": "application/x-npy"})
    depth = np.load(io.BytesIO(n.content))
    np.testing.assert_array_equal(np.isnan(depth), (rgba[..., 3] == 0) & ~(np.nan_to_num(depth, nan=1) == 0))


def test_camera_path_gives_novel_cameras_that_render_as_they_are(ready) -> None:
    client, sid, scene, _ = ready
    r = client.get(f"/v1/scenes/{sid}/camera-path?path=orbit&frames=8")
    assert r.status_code == 200 and r.json()["path"] == "orbit"
    frames = r.json()["frames"]
    assert len(frames) == 8 and set(frames[0]) == set(RenderCamera.model_fields)
    # where cmc.geometry.camera_paths puts them: the orbit of the baked MPIs' reference cameras, as in the video
    manifest = client.get(f"/v1/scenes/{sid}/mpi").json()
    refs = np.array([m["world_from_cam"] for m in manifest["mpis"]])
    poses = np.array([convert_pose(np.array(f["transform_matrix"]), "opengl", "opencv") for f in frames])
    np.testing.assert_allclose(poses, orbit_path(refs, 8), atol=1e-9)
    baked = BakedScene.load(client.app.state.services.storage.path(f"{sid}/baked"))
    K, video_poses, _, _ = path_cameras(baked, "orbit", 8)
    np.testing.assert_allclose(poses, video_poses, atol=1e-6)
    assert [frames[0][k] for k in ("fl_x", "fl_y", "cx", "cy")] == pytest.approx([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    offsets = np.linalg.norm(poses[:, None, :3, 3] - scene.cameras.centers[None], axis=-1)
    assert offsets.min() > 0.1 * capture_radius(scene.cameras.world_from_cam)  # no input camera: novel views
    # the scene's centre (on the mean camera's axis, halfway in disparity) is seen near the image centre
    mean = mean_pose(refs)
    centre = mean[:3, 3] + mean[:3, 2] * 2 / (1 / manifest["near"] + 1 / manifest["far"])
    uv, z = Cameras(np.repeat(K[None], 8, axis=0), poses, 96, 72).project(centre[None])
    assert (z > 0).all() and np.abs(uv[:, 0] - [48, 36]).max() < 0.15 * 96
    # a path camera is a render body as it is: POST it unchanged
    img = client.post(f"/v1/scenes/{sid}/render", json=frames[3])
    assert img.status_code == 200 and Image.open(io.BytesIO(img.content)).size == (96, 72)
    spiral = client.get(f"/v1/scenes/{sid}/camera-path?path=spiral&frames=5&convention=opencv").json()["frames"]
    assert len(spiral) == 5 and spiral[2]["convention"] == "opencv"
    expected = camera_path("spiral", refs, manifest["near"], manifest["far"], 5)[2]
    np.testing.assert_allclose(spiral[2]["transform_matrix"], expected, atol=1e-9)
    assert client.get(f"/v1/scenes/{sid}/camera-path?frames=0").status_code == 422


def test_render_content_negotiation_and_bad_cameras(ready) -> None:
    client, sid, _, novel = ready
    body = render_body(novel)
    jpeg = client.post(f"/v1/scenes/{sid}/render", json=body, headers={"Accept": "image/jpeg"})
    assert jpeg.headers["content-type"] == "image/jpeg" and jpeg.content[:2] == b"\xff\xd8"
    pref = client.post(f"/v1/scenes/{sid}/render", json=body, headers={"Accept": "image/png;q=0.5, image/jpeg"})
    assert pref.headers["content-type"] == "image/jpeg"
    bad = client.post(f"/v1/scenes/{sid}/render", json=body, headers={"Accept": "text/html"})
    assert bad.status_code == 406 and bad.json()["error"]["code"] == "not_acceptable"
    skew = {**body, "transform_matrix": (np.array(body["transform_matrix"]) * [[1, 2, 1, 1]] * 1).tolist()}
    r = client.post(f"/v1/scenes/{sid}/render", json=skew)
    assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_cameras"
    for route in ("render", "depth"):  # intrinsics that underflow to a singular matrix
        tiny = client.post(f"/v1/scenes/{sid}/{route}", json={**body, "fl_x": 1e-300})
        assert tiny.status_code == 422 and tiny.json()["error"]["code"] == "invalid_cameras", tiny.text
    huge = client.post(f"/v1/scenes/{sid}/render", json={**body, "w": 8000, "h": 8000})
    assert huge.status_code == 422 and huge.json()["error"]["code"] == "render_too_large"
    missing = client.post(f"/v1/scenes/{sid}/render", json={"fl_x": 10})
    assert missing.status_code == 422 and missing.json()["error"]["code"] == "validation_error"
    assert {d["field"] for d in missing.json()["error"]["details"]} >= {"body.transform_matrix", "body.w", "body.h"}
    assert missing.json()["error"]["message"] == "the request is not valid"
    # the camera as JSON text without Content-Type (curl -d sends a form type): say what is wrong
    for headers in ({}, {"Content-Type": "application/x-www-form-urlencoded"}):
        untyped = client.post(f"/v1/scenes/{sid}/render", content=json.dumps(body), headers=headers)
        assert untyped.status_code == 422, untyped.text
        assert "Content-Type: application/json" in untyped.json()["error"]["message"], untyped.text


def test_cameras_round_trip_in_the_upload_format(ready) -> None:
    client, sid, scene, _ = ready
    gl = client.get(f"/v1/scenes/{sid}/cameras").json()
    assert gl["convention"] == "opengl" and (gl["w"], gl["h"]) == (96, 72)
    assert [f["file_path"] for f in gl["frames"]] == ["view0.png", "view1.png", "view2.png"]
    for i, f in enumerate(gl["frames"]):
        expected = convert_pose(scene.cameras.world_from_cam[i], "opencv", "opengl")
        np.testing.assert_allclose(f["transform_matrix"], expected, atol=1e-6)
        assert f["near"] < f["far"]
    cv = client.get(f"/v1/scenes/{sid}/cameras?convention=opencv").json()
    np.testing.assert_allclose(cv["frames"][0]["transform_matrix"], scene.cameras.world_from_cam[0], atol=1e-6)


def test_baked_mpi_files(ready) -> None:
    client, sid, _, _ = ready
    manifest = client.get(f"/v1/scenes/{sid}/mpi").json()
    assert manifest["format"] == "cmc-mpi" and len(manifest["mpis"]) == 3
    assert client.get(f"/v1/scenes/{sid}/mpi/mpi.json").json() == manifest
    atlas = client.get(f"/v1/scenes/{sid}/mpi/{manifest['mpis'][0]['atlas']}")
    assert atlas.status_code == 200 and Image.open(io.BytesIO(atlas.content)).mode == "RGBA"
    for name in ("cameras.json", "..%2Fscene%2Fcameras.json", "mpi_99.png"):
        assert client.get(f"/v1/scenes/{sid}/mpi/{name}").status_code == 404


def test_video_is_built_by_the_runner_once_then_served_from_storage(ready) -> None:
    client, sid, _, _ = ready
    first = client.get(f"/v1/scenes/{sid}/video?path=orbit")
    assert first.status_code == 202 and first.json()["status"] == "building" and first.headers["retry-after"] == "5"
    t0 = time.time()
    while (r := client.get(f"/v1/scenes/{sid}/video?path=orbit")).status_code == 202:
        assert 0 <= r.json()["progress"] <= 1
        assert time.time() - t0 < 180
        time.sleep(0.5)
    assert r.status_code == 200 and r.headers["content-type"] == "video/mp4"
    assert r.content[4:8] == b"ftyp" and len(r.content) > 1000
    mp4 = client.app.state.services.storage.path(f"{sid}/videos/orbit.mp4")
    assert mp4.exists() and not mp4.with_suffix(".json").exists()
    built_at = mp4.stat().st_mtime
    again = client.get(f"/v1/scenes/{sid}/video?path=orbit")
    assert again.content == r.content and mp4.stat().st_mtime == built_at  # cached, not rebuilt
    assert client.get(f"/v1/scenes/{sid}/video?path=zoom").status_code == 422


def test_viewer_page_needs_no_key(api) -> None:
    client = api(api_keys="secret")
    r = client.get("/v1/scenes/0123456789abcdef0123456789abcdef/viewer")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "webgl2" in r.text and "script-src 'unsafe-inline'" in r.headers["content-security-policy"]
    assert client.get("/v1/scenes/0123456789abcdef0123456789abcdef").status_code == 401


def test_operations_endpoints(ready) -> None:
    client, _, _, _ = ready
    assert client.get("/healthz").json() == {"status": "ok", "checks": {}}
    ready_body = client.get("/readyz").json()
    assert ready_body["checks"] == {"database": "ok", "storage": "ok", "queue": "ok"}
    text = client.get("/metrics").text
    assert 'cmc_jobs{status="ready"} 1.0' in text
    assert 'cmc_job_duration_seconds_count{status="ready"} 1.0' in text
    assert 'cmc_queue_depth{queue="embedded"} 0.0' in text
    assert 'cmc_http_requests_total{method="GET",route="/v1/scenes/{scene_id}",status="200"}' in text


def _baked_ready_scene(app, owner: str = "local") -> tuple[str, dict]:
    """A ready scene whose baked MPI comes from an untrained model (no job ran), and a camera."""
    from cmc.config import preset_config
    from cmc.data.datasets import synthetic_scene
    from cmc.method.training import Trainer
    from cmc.serving.baking import bake

    svc = app.state.services
    rec, _ = svc.store.create(owner, {}, ["a.png", "b.png"], ["00.png", "01.png"], False)
    assert svc.store.claim(rec.id, "poses", "test", 60) is not None
    assert svc.store.advance(rec.id, "test", "done", "ready")
    scene = synthetic_scene(num_views=2, width=32, height=24)
    bake(
        Trainer(scene, preset_config("fast", steps=1, rays_per_view=64, unseen_rays=64)).model,
        svc.storage.path(f"{rec.id}/baked"),
    )
    return rec.id, render_body(scene.cameras)


def test_renders_never_hold_up_probes_and_status(api, monkeypatch) -> None:
    from cmc.serving.baking import BakedScene

    app = create_app(settings_for(api.storage.parent, render_concurrency=2, render_queue=4), queue=RecordingQueue())
    sid, camera = _baked_ready_scene(app)
    drawn = BakedScene.render

    def slow_render(self, *args, **kwargs):
        time.sleep(0.5)
        return drawn(self, *args, **kwargs)

    monkeypatch.setattr(BakedScene, "render", slow_render)
    with live_server(app) as port, httpx2.Client(base_url=f"http://127.0.0.1:{port}", timeout=60) as client:
        assert client.post(f"/v1/scenes/{sid}/render", json=camera).status_code == 200  # loads the scene
        with ThreadPoolExecutor(48) as pool:
            renders = [pool.submit(client.post, f"/v1/scenes/{sid}/render", json=camera) for _ in range(48)]
            time.sleep(0.3)  # all of them arrived
            for path in ("/healthz", "/readyz", f"/v1/scenes/{sid}"):
                t0 = time.perf_counter()
                assert client.get(path).status_code == 200
                assert time.perf_counter() - t0 < 0.5, path
            answers = [r.result() for r in renders]
    drawn_ok = [r for r in answers if r.status_code == 200]
    busy = [r for r in answers if r.status_code == 503]
    assert len(drawn_ok) + len(busy) == 48 and 6 <= len(drawn_ok) < 48  # 2 drawing + 4 waiting at a time
    assert all(r.content[:4] == b"\x89PNG" for r in drawn_ok)
    assert {r.json()["error"]["code"] for r in busy} == {"renderer_busy"}
    assert {r.headers["retry-after"] for r in busy} == {"1"}


# -- uploads, limits, auth: nothing trains ------------------------------------------------------------


@pytest.fixture
def api(tmp_path):
    queue = RecordingQueue()

    def make(**overrides) -> TestClient:
        return TestClient(create_app(settings_for(tmp_path, **overrides), queue=queue))

    make.queue = queue  # type: ignore[attr-defined]
    make.storage = tmp_path / "storage"  # type: ignore[attr-defined]
    return make


def stored_scenes(storage: Path) -> list[str]:
    return sorted(p.name for p in storage.iterdir() if not p.name.startswith(".")) if storage.exists() else []


def test_upload_is_queued_on_the_cpu_phase(api) -> None:
    parts, _, _ = synthetic_upload()
    client = api()
    r = client.post("/v1/scenes", files=parts)
    assert r.status_code == 202 and r.headers["location"] == f"/v1/scenes/{r.json()['id']}"
    body = r.json()
    assert body["status"] == "queued" and body["progress"] == 0.0
    assert api.queue.sent == [(body["id"], "poses")]
    files = sorted(p.name for p in (api.storage / body["id"] / "uploads").iterdir())
    assert files == ["00.png", "01.png", "02.png", "cameras.json"]  # our names, never the client's
    cams = json.loads((api.storage / body["id"] / "uploads" / "cameras.json").read_text())
    assert [f["file_path"] for f in cams["frames"]] == ["00.png", "01.png", "02.png"]
    camera = {"transform_matrix": np.eye(4).tolist(), "fl_x": 50, "w": 8, "h": 8}
    not_ready = client.post(f"/v1/scenes/{body['id']}/render", json=camera)
    assert not_ready.status_code == 409 and not_ready.json()["error"]["details"] == {"status": "queued"}
    assert client.get(f"/v1/scenes/{body['id']}/cameras").status_code == 409


def _replace(parts: list, index: int, name: str, data: bytes) -> list:
    parts = list(parts)
    parts[index] = ("images", (name, data, "image/jpeg"))
    return parts


@pytest.mark.parametrize(
    "case, status, code",
    [
        ("too_few", 422, "too_few_images"),
        ("too_many", 422, "too_many_images"),
        ("not_an_image", 415, "unsupported_image"),
        ("empty", 422, "invalid_images"),
        ("truncated", 422, "invalid_images"),
        ("bytes", 413, "image_too_large"),
        ("pixels", 413, "image_too_large"),
        ("sizes", 422, "invalid_images"),
        ("options", 422, "invalid_options"),
        ("steps", 422, "invalid_options"),
        ("cameras_json", 422, "invalid_cameras"),
        ("cameras_names", 422, "invalid_cameras"),
        ("cameras_deep", 422, "invalid_cameras"),
        ("request", 413, "payload_too_large"),
        ("not_multipart", 415, "unsupported_media_type"),
    ],
)
def test_bad_uploads_are_refused_and_nothing_is_kept(api, case: str, status: int, code: str) -> None:
    parts, scene, _ = synthetic_upload()
    overrides: dict = {}
    images, rest = parts[:3], parts[3:]
    jpeg = io.BytesIO()
    Image.fromarray((scene.images[0] * 255).astype(np.uint8)).save(jpeg, "JPEG")
    if case == "too_few":
        parts = images[:2] + rest
    elif case == "too_many":
        parts = images + [images[0]] + rest
    elif case == "not_an_image":
        parts = _replace(parts, 1, "view1.png", b"GIF89a this is text, not a photo")
    elif case == "empty":
        parts = _replace(parts, 1, "view1.png", b"")
    elif case == "truncated":
        parts = _replace(parts, 1, "view1.png", jpeg.getvalue()[: len(jpeg.getvalue()) // 2])
    elif case == "bytes":
        overrides["max_image_bytes"] = 4096
    elif case == "pixels":
        overrides["max_image_pixels"] = 96 * 72 - 1
    elif case == "sizes":
        parts = _replace(parts, 2, "view2.png", png(np.zeros((96, 72, 3))))
    elif case == "options":
        parts = images + rest[:1] + [("options", (None, '{"preset": "fast", "colour": "blue"}'))]
    elif case == "steps":
        parts = images + rest[:1] + [("options", (None, '{"steps": 1000000}'))]
    elif case == "cameras_json":
        parts = images + [("cameras", ("c.json", b"{not json", "application/json"))] + rest[1:]
    elif case == "cameras_names":
        cams = json.loads(rest[0][1][1])
        cams["frames"][2]["file_path"] = "someone_else.png"
        parts = images + [("cameras", ("c.json", json.dumps(cams).encode(), "application/json"))] + rest[1:]
    elif case == "cameras_deep":  # nested too deeply for Python's JSON parser
        parts = images + [("cameras", ("c.json", b"[" * 100_000, "application/json"))] + rest[1:]
    elif case == "request":  # every part within its limit, the whole over the request limit
        overrides.update(max_image_bytes=40_000, max_cameras_bytes=20_000)
        parts = parts + [("padding", (None, b"x" * 200_000))]
    client = api(**overrides)
    if case == "not_multipart":
        r = client.post("/v1/scenes", json={"images": []})
    else:
        r = client.post("/v1/scenes", files=parts)
    assert r.status_code == status, r.text
    error = r.json()["error"]
    assert error["code"] == code and error["message"]
    if case in ("not_an_image", "truncated", "empty"):
        assert "view1.png" in error["message"]  # the client's name, not ours
    assert api.queue.sent == [] and stored_scenes(api.storage) == []


def test_options_are_validated_with_field_details(api) -> None:
    parts, _, _ = synthetic_upload()
    r = api().post("/v1/scenes", files=parts[:4] + [("options", (None, '{"preset": "slow", "resolution": 10}'))])
    assert r.status_code == 422
    assert {d["field"] for d in r.json()["error"]["details"]} == {"preset", "resolution"}


def test_idempotency_key(api) -> None:
    parts, _, _ = synthetic_upload()
    client = api()
    first = client.post("/v1/scenes", files=parts, headers={"Idempotency-Key": "upload-1"})
    again = client.post("/v1/scenes", files=parts, headers={"Idempotency-Key": "upload-1"})
    assert first.status_code == again.status_code == 202
    assert again.json()["id"] == first.json()["id"] and again.headers["idempotent-replayed"] == "true"
    other = client.post("/v1/scenes", files=parts[:3], headers={"Idempotency-Key": "upload-1"})
    assert other.status_code == 409 and other.json()["error"]["code"] == "idempotency_conflict"
    assert len(api.queue.sent) == 1 and stored_scenes(api.storage) == [first.json()["id"]]


def test_api_keys_scope_scenes_to_their_owner(api, tmp_path: Path) -> None:
    keys_file = tmp_path / "keys.txt"
    keys_file.write_text(f"# the app\n{key_digest('key-b')}  # b\n")
    client = api(api_keys="key-a", api_keys_file=keys_file)
    parts, _, _ = synthetic_upload()
    a, b = {"Authorization": "Bearer key-a"}, {"Authorization": "Bearer key-b"}
    no_key = client.post("/v1/scenes", files=parts)
    assert no_key.status_code == 401 and no_key.json()["error"]["code"] == "unauthorized"
    assert client.get("/v1/scenes", headers={"Authorization": "Bearer nope"}).status_code == 401
    assert client.get("/v1/scenes", headers={"Authorization": "Basic a2V5LWE="}).status_code == 401
    sid = client.post("/v1/scenes", files=parts, headers=a).json()["id"]
    assert client.get(f"/v1/scenes/{sid}", headers=a).status_code == 200
    for method, path in (("GET", ""), ("GET", "/cameras"), ("DELETE", ""), ("GET", "/mpi")):
        r = client.request(method, f"/v1/scenes/{sid}{path}", headers=b)
        assert r.status_code == 404 and r.json()["error"]["code"] == "not_found", (method, path)
    assert [s["id"] for s in client.get("/v1/scenes", headers=a).json()["items"]] == [sid]
    assert client.get("/v1/scenes", headers=b).json()["items"] == []
    assert client.get("/healthz").status_code == 200  # probes need no key


def test_request_bodies_are_refused_before_they_are_read(api) -> None:
    app = create_app(settings_for(api.storage.parent, api_keys="key-a", max_json_bytes=4096), queue=RecordingQueue())
    render = "POST /v1/scenes/0123456789abcdef0123456789abcdef/render HTTP/1.1\nHost: 127.0.0.1\n"
    json_head = render + "Content-Type: application/json\n"
    with live_server(app) as port:
        # Content-Length announces 100 MB; 2 bytes are sent, and the answer comes without the rest
        status, body, seconds = raw_exchange(port, json_head + "Content-Length: 100000000\n", [b"{}"])
        assert status == 401 and body["error"]["code"] == "unauthorized" and seconds < 1
        status, _, _ = raw_exchange(port, render + "Transfer-Encoding: chunked\n", [b"2\r\n{}\r\n"])
        assert status == 401  # a body of unannounced length, too
        keyed = json_head + "Authorization: Bearer key-a\n"
        status, body, seconds = raw_exchange(port, keyed + "Content-Length: 100000000\n", [b"{}"])
        assert status == 413 and body["error"]["code"] == "payload_too_large" and seconds < 1
        # streamed without a length: refused once the bytes cross the limit, not at the end
        chunks = [b"400\r\n" + b" " * 1024 + b"\r\n"] * 5
        status, body, seconds = raw_exchange(port, keyed + "Transfer-Encoding: chunked\n", chunks)
        assert status == 413 and body["error"]["code"] == "payload_too_large" and seconds < 1
    # within the limit, a keyed body goes on to the route (a scene that does not exist)
    camera = {"transform_matrix": np.eye(4).tolist(), "fl_x": 50, "w": 8, "h": 8}
    r = TestClient(app).post(render.split()[1], json=camera, headers={"Authorization": "Bearer key-a"})
    assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"


def test_open_mode_answers_only_local_hosts_and_pages(api) -> None:
    client = api(allowed_hosts="mybox.lan")
    for host in ("127.0.0.1:8000", "localhost", "LOCALHOST:1", "[::1]:8000", "mybox.lan:8000"):
        assert client.get("/healthz", headers={"Host": host}).status_code == 200, host
    for host in ("attacker.example", "localhost.attacker.example:8000", "127.0.0.1.nip.io", "[::1"):
        r = client.get("/v1/scenes", headers={"Host": host})  # DNS rebinding: another name, this address
        assert r.status_code == 421 and r.json()["error"]["code"] == "host_not_allowed", host
    parts, _, _ = synthetic_upload()
    local = {"Host": "127.0.0.1:8000"}
    for page in ({"Origin": "https://attacker.example"}, {"Origin": "null"}, {"Sec-Fetch-Site": "cross-site"}):
        r = client.post("/v1/scenes", files=parts, headers={**local, **page})  # a form on another site
        assert r.status_code == 403 and r.json()["error"]["code"] == "cross_site_request", page
    assert api.queue.sent == [] and stored_scenes(api.storage) == []
    same_site = {"Origin": "http://localhost:8000", "Sec-Fetch-Site": "same-site"}
    sid = client.post("/v1/scenes", files=parts, headers={**local, **same_site}).json()["id"]
    assert client.post("/v1/scenes", files=parts, headers=local).status_code == 202  # curl, scripts: no Origin
    gone = client.delete(f"/v1/scenes/{sid}", headers={**local, "Origin": "http://attacker.example:8000"})
    assert gone.status_code == 403
    # with API keys, neither Host nor Origin matters (the key does)
    keyed = api(api_keys="key-a", allowed_hosts="")
    key = {"Authorization": "Bearer key-a", "Host": "api.example.com", "Origin": "https://app.example.com"}
    assert keyed.post("/v1/scenes", files=parts, headers=key).status_code == 202


def test_list_is_paginated_newest_first(api) -> None:
    client = api()
    parts, _, _ = synthetic_upload()
    ids = [client.post("/v1/scenes", files=parts).json()["id"] for _ in range(5)]
    seen, cursor = [], None
    while True:
        page = client.get("/v1/scenes", params={"limit": 2, **({"cursor": cursor} if cursor else {})}).json()
        assert len(page["items"]) <= 2
        seen += [s["id"] for s in page["items"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == ids[::-1]
    assert client.get("/v1/scenes", params={"cursor": "garbage"}).json()["error"]["code"] == "invalid_cursor"
    assert client.get("/v1/scenes", params={"limit": 0}).status_code == 422


def test_delete_removes_record_and_data(api) -> None:
    client = api()
    parts, _, _ = synthetic_upload()
    sid = client.post("/v1/scenes", files=parts).json()["id"]
    assert client.delete(f"/v1/scenes/{sid}").status_code == 204
    assert client.get(f"/v1/scenes/{sid}").status_code == 404
    assert client.delete(f"/v1/scenes/{sid}").status_code == 404
    assert stored_scenes(api.storage) == []


def test_errors_have_one_shape(api) -> None:
    client = api()
    for r, status in ((client.get("/nowhere"), 404), (client.put("/v1/scenes"), 405)):
        assert r.status_code == status
        assert set(r.json()["error"]) == {"code", "message", "details"}


def test_queue_outage_is_a_clean_503(api) -> None:
    class DownQueue(RecordingQueue):
        def submit(self, scene_id: str, phase: str) -> None:
            raise ConnectionError("broker down")

    client = TestClient(create_app(settings_for(api.storage.parent), queue=DownQueue()))
    parts, _, _ = synthetic_upload()
    r = client.post("/v1/scenes", files=parts, headers={"Idempotency-Key": "k"})
    assert r.status_code == 503 and r.json()["error"]["code"] == "queue_unavailable"
    assert client.get("/v1/scenes").json()["items"] == [] and stored_scenes(api.storage) == []


# -- quotas and rate limits per API key ---------------------------------------------------------------

KEY_A, KEY_B = {"Authorization": "Bearer key-a"}, {"Authorization": "Bearer key-b"}
NO_SCENE = "/v1/scenes/0123456789abcdef0123456789abcdef"


class Clock:
    """Seconds that move only when a test says so (the limiter's clock)."""

    def __init__(self) -> None:
        self.t = 1_000_000.0

    def __call__(self) -> float:
        return self.t


def quota_app(tmp: Path, limiter=None, queue=None, **limits):
    """An app with API keys key-a and key-b, the given limits, a recording queue and (by default)
    the in-memory limiter on a clock the test moves (``app.clock``)."""
    clock = Clock()
    settings = settings_for(tmp, api_keys="key-a,key-b", **limits)
    app = create_app(settings, queue=queue or RecordingQueue(), limiter=limiter or MemoryLimiter(clock))
    app.clock = clock  # type: ignore[attr-defined]
    return app


def rate_fields(r: httpx2.Response) -> tuple[str, str, str] | None:
    """(RateLimit-Limit, -Remaining, -Reset) of an answer, or None when it has none."""
    if "ratelimit-limit" not in r.headers:
        return None
    return r.headers["ratelimit-limit"], r.headers["ratelimit-remaining"], r.headers["ratelimit-reset"]


def assert_refused(r: httpx2.Response, code: str, limit: str, maximum: int, retry_after: int) -> None:
    assert r.status_code == 429, r.text
    assert r.json()["error"] == {
        "code": code,
        "message": r.json()["error"]["message"],
        "details": {"limit": limit, "maximum": maximum, "retry_after": retry_after},
    }
    assert f"{maximum} " in r.json()["error"]["message"]
    assert r.headers["retry-after"] == str(retry_after)
    assert rate_fields(r) == (str(maximum), "0", str(retry_after))


def test_quota_renders_per_second_per_key(tmp_path: Path) -> None:
    app = quota_app(tmp_path, max_renders_per_second=3)
    sid, camera = _baked_ready_scene(app, owner=key_digest("key-a")[:16])
    client = TestClient(app)
    ok = client.post(f"/v1/scenes/{sid}/render", json=camera, headers=KEY_A)
    assert ok.status_code == 200 and rate_fields(ok) == ("3", "2", "1")
    # counted when they arrive, whatever the answer; depth shares the limit with render
    missing = client.post(f"{NO_SCENE}/render", json=camera, headers=KEY_A)
    assert missing.status_code == 404 and rate_fields(missing) == ("3", "1", "1")
    assert client.post(f"/v1/scenes/{sid}/depth", json=camera, headers=KEY_A).status_code == 200
    refused = client.post(f"/v1/scenes/{sid}/render", json=camera, headers=KEY_A)
    assert_refused(refused, "render_rate_limited", "renders_per_second", 3, 1)
    depth = client.post(f"/v1/scenes/{sid}/depth", json=camera, headers=KEY_A)
    assert_refused(depth, "render_rate_limited", "renders_per_second", 3, 1)
    assert client.get(f"/v1/scenes/{sid}", headers=KEY_A).status_code == 200  # status polls are not limited
    assert client.post(f"{NO_SCENE}/render", json=camera, headers=KEY_B).status_code == 404  # key-b: its own
    app.clock.t += 1.0  # the second is over
    again = client.post(f"/v1/scenes/{sid}/render", json=camera, headers=KEY_A)
    assert again.status_code == 200 and rate_fields(again) == ("3", "2", "1")
    text = client.get("/metrics").text
    assert 'cmc_rate_limited_total{limit="renders_per_second"} 2.0' in text
    assert 'cmc_rate_limited_total{limit="concurrent_jobs"} 0.0' in text
    assert 'cmc_http_requests_total{method="POST",route="/v1/scenes/{scene_id}/render",status="429"} 1.0' in text


def test_quota_concurrent_jobs_per_key(tmp_path: Path) -> None:
    app = quota_app(tmp_path, max_concurrent_jobs=2)
    client, store = TestClient(app), app.state.services.store
    parts, _, _ = synthetic_upload()
    first = client.post("/v1/scenes", files=parts, headers={**KEY_A, "Idempotency-Key": "first"})
    # the limit closest to refusing: 1 of 2 unfinished jobs left (jobs per day: 99 of 100)
    assert first.status_code == 202 and rate_fields(first) == ("2", "1", "60")
    bad = client.post("/v1/scenes", files=_replace(parts, 0, "a.jpg", b"not an image"), headers=KEY_A)
    assert bad.status_code == 415 and rate_fields(bad) is None  # a refused upload gives its place back
    second = client.post("/v1/scenes", files=parts, headers=KEY_A)
    assert second.status_code == 202 and rate_fields(second) == ("2", "0", "60")
    # no job has an ETA yet: Retry-After is a minute; then the shortest ETA of the key's jobs
    refused = client.post("/v1/scenes", files=parts, headers=KEY_A)
    assert_refused(refused, "too_many_concurrent_jobs", "concurrent_jobs", 2, 60)
    sid = second.json()["id"]
    assert store.claim(sid, "poses", "worker", 60) is not None
    store.heartbeat(sid, "worker", 60, status="estimating_poses", eta_seconds=41.2)
    third = client.post("/v1/scenes", files=parts, headers=KEY_A)
    assert_refused(third, "too_many_concurrent_jobs", "concurrent_jobs", 2, 42)
    assert len(app.state.services.queue.sent) == 2 and len(stored_scenes(tmp_path / "storage")) == 2
    # a retry of an upload that made its scene is answered with it, not refused
    replay = client.post("/v1/scenes", files=parts, headers={**KEY_A, "Idempotency-Key": "first"})
    assert replay.status_code == 202 and replay.headers["idempotent-replayed"] == "true"
    assert client.post("/v1/scenes", files=parts, headers=KEY_B).status_code == 202  # key-b: its own
    # a job that ends frees its place (failed, ready or deleted) once the database is the only
    # count of it: RECORD_HOLD_S after its upload
    store.fail(sid, "training_failed", "test")
    assert client.post("/v1/scenes", files=parts, headers=KEY_A).status_code == 429
    app.clock.t += RECORD_HOLD_S
    assert client.post("/v1/scenes", files=parts, headers=KEY_A).status_code == 202
    assert client.post("/v1/scenes", files=parts, headers=KEY_A).status_code == 429
    assert client.delete(f"/v1/scenes/{first.json()['id']}", headers=KEY_A).status_code == 204
    assert client.post("/v1/scenes", files=parts, headers=KEY_A).status_code == 202
    assert 'cmc_rate_limited_total{limit="concurrent_jobs"} 4.0' in client.get("/metrics").text


def test_quota_jobs_per_day_per_key(tmp_path: Path) -> None:
    app = quota_app(tmp_path, max_jobs_per_day=2, max_concurrent_jobs=0)
    client = TestClient(app)
    parts, _, _ = synthetic_upload()
    one = client.post("/v1/scenes", files=parts, headers=KEY_A)
    assert one.status_code == 202 and rate_fields(one) == ("2", "1", "86400")
    app.clock.t += 3600
    two = client.post("/v1/scenes", files=parts, headers=KEY_A)
    assert two.status_code == 202 and rate_fields(two) == ("2", "0", "82800")  # the first leaves in 23 h
    assert client.delete(f"/v1/scenes/{one.json()['id']}", headers=KEY_A).status_code == 204  # still counted
    app.clock.t += 600
    refused = client.post("/v1/scenes", files=parts, headers=KEY_A)
    assert_refused(refused, "daily_job_quota_exceeded", "jobs_per_day", 2, 86400 - 3600 - 600)
    assert client.post("/v1/scenes", files=parts, headers=KEY_B).status_code == 202
    app.clock.t += 86400 - 3600 - 600  # 24 h after the first upload
    three = client.post("/v1/scenes", files=parts, headers=KEY_A)
    assert three.status_code == 202 and rate_fields(three) == ("2", "0", "3600")
    assert 'cmc_rate_limited_total{limit="jobs_per_day"} 1.0' in client.get("/metrics").text


def test_quota_refuses_an_upload_before_reading_its_photos(tmp_path: Path) -> None:
    app = quota_app(tmp_path, max_concurrent_jobs=1)
    parts, _, _ = synthetic_upload()
    assert TestClient(app).post("/v1/scenes", files=parts, headers=KEY_A).status_code == 202
    head = "POST /v1/scenes HTTP/1.1\nHost: 127.0.0.1\nAuthorization: Bearer key-a\n"
    head += "Content-Type: multipart/form-data; boundary=b\nContent-Length: 80000000\n"
    with live_server(app) as port:  # 80 MB announced, 100 bytes sent: the answer comes without the rest
        status, body, seconds = raw_exchange(port, head, [b"--b\r\n" + b" " * 96])
    assert status == 429 and body["error"]["code"] == "too_many_concurrent_jobs" and seconds < 1


def test_quota_open_mode_is_unlimited(api) -> None:
    client = api(max_concurrent_jobs=1, max_jobs_per_day=1, max_renders_per_second=1)  # no API keys
    parts, _, _ = synthetic_upload()
    uploads = [client.post("/v1/scenes", files=parts) for _ in range(3)]
    assert [r.status_code for r in uploads] == [202] * 3 and not any(map(rate_fields, uploads))
    camera = {"transform_matrix": np.eye(4).tolist(), "fl_x": 50, "w": 8, "h": 8}
    renders = [client.post(f"{NO_SCENE}/render", json=camera) for _ in range(3)]
    assert [r.status_code for r in renders] == [404] * 3 and not any(map(rate_fields, renders))


def test_quota_in_redis_holds_across_api_replicas(tmp_path: Path, redis_prefix: str) -> None:
    clock = Clock()
    limits = dict(max_concurrent_jobs=2, max_renders_per_second=3)
    # two API processes' worth of apps: one database and storage, one Redis, a limiter client each
    replicas = [quota_app(tmp_path, RedisLimiter(REDIS_URL, prefix=redis_prefix, clock=clock), **limits) for _ in "ab"]
    parts, _, _ = synthetic_upload()
    camera = {"transform_matrix": np.eye(4).tolist(), "fl_x": 50, "w": 8, "h": 8}
    with live_server(replicas[0]) as port_a, live_server(replicas[1]) as port_b:
        clients = [httpx2.Client(base_url=f"http://127.0.0.1:{p}", headers=KEY_A, timeout=30) for p in (port_a, port_b)]
        # six uploads at once, three to each replica: exactly two jobs are made
        with ThreadPoolExecutor(6) as pool:
            answers = list(pool.map(lambda k: clients[k % 2].post("/v1/scenes", files=parts), range(6)))
        assert sorted(r.status_code for r in answers) == [202, 202, 429, 429, 429, 429], [r.text for r in answers]
        assert {r.json()["error"]["code"] for r in answers if r.status_code == 429} == {"too_many_concurrent_jobs"}
        renders = [clients[k % 2].post(f"{NO_SCENE}/render", json=camera) for k in range(4)]
        assert [r.status_code for r in renders] == [404, 404, 404, 429]
        assert [rate_fields(r)[1] for r in renders] == ["2", "1", "0", "0"]
        clock.t += 1.0
        assert clients[1].post(f"{NO_SCENE}/render", json=camera).status_code == 404
        for c in clients:
            c.close()


def test_quota_unreachable_redis_lets_requests_through(tmp_path: Path) -> None:
    limiter = RedisLimiter("redis://127.0.0.1:1/0", timeout_s=0.2)
    client = TestClient(quota_app(tmp_path, limiter, max_concurrent_jobs=1, max_renders_per_second=1))
    parts, _, _ = synthetic_upload()
    uploads = [client.post("/v1/scenes", files=parts, headers=KEY_A) for _ in range(2)]
    assert [r.status_code for r in uploads] == [202, 202] and not any(map(rate_fields, uploads))
    camera = {"transform_matrix": np.eye(4).tolist(), "fl_x": 50, "w": 8, "h": 8}
    assert [client.post(f"{NO_SCENE}/render", json=camera, headers=KEY_A).status_code for _ in range(2)] == [404] * 2


def test_negotiate() -> None:
    offered = ["image/png", "image/jpeg"]
    assert negotiate(None, offered) == "image/png"
    assert negotiate("*/*", offered) == "image/png"
    assert negotiate("image/*;q=0.8, image/jpeg", offered) == "image/jpeg"
    assert negotiate("image/jpeg;q=0, image/png;q=0.1", offered) == "image/png"
    assert negotiate("application/json", offered) is None


# -- the embedded runner: failures, cancellation, restarts -------------------------------------------


def test_failed_pose_estimation_names_the_clients_photos(tmp_path: Path) -> None:
    blank = png(np.full((72, 96, 3), 0.5))
    grey = [png(np.full((72, 96, 3), 0.4))] + [blank, blank]
    parts = [("images", (f"IMG_{i}.png", grey[i], "image/png")) for i in range(3)]
    with TestClient(create_app(settings_for(tmp_path))) as client:
        sid = client.post("/v1/scenes", files=parts).json()["id"]
        body = wait_for(client, sid, ("failed", "ready"), timeout=120)
    assert body["status"] == "failed"
    assert body["error"]["code"] in ("pose_estimation_failed", "invalid_images")
    assert "IMG_1.png" in body["error"]["message"] and "01.png" not in body["error"]["message"]


def test_delete_cancels_a_running_job_within_seconds(tmp_path: Path) -> None:
    parts, _, _ = synthetic_upload(steps=5000)
    app = create_app(settings_for(tmp_path))
    runner = app.state.services.queue
    with TestClient(app) as client:
        sid = client.post("/v1/scenes", files=parts).json()["id"]
        t0 = time.time()
        while True:
            body = client.get(f"/v1/scenes/{sid}").json()
            if body["status"] == "training" and body["progress"] > 0:
                break
            assert time.time() - t0 < 120, body
            time.sleep(0.2)
        t_delete = time.time()
        assert client.delete(f"/v1/scenes/{sid}").status_code == 204
        store = app.state.services.store
        while store.get(sid, include_deleted=True).lease_owner is not None:
            assert time.time() - t_delete < 10, "the job did not stop within 10 s"
            time.sleep(0.1)
        time.sleep(0.5)
        assert not (tmp_path / "storage" / sid).exists()
        assert runner.depth() == {"embedded": 0}
        assert store.get(sid, include_deleted=True).status == "cancelled"


def _stopped_mid_training(settings: Settings) -> str:
    """A 40-step job's id, its app stopped once the job had passed 30 % of its training (the job
    checkpointed and stays unfinished)."""
    parts, _, _ = synthetic_upload(steps=40)
    with TestClient(create_app(settings)) as client:
        sid = client.post("/v1/scenes", files=parts).json()["id"]
        t0 = time.time()
        while client.get(f"/v1/scenes/{sid}").json()["progress"] < 0.3:
            assert time.time() - t0 < 180
            time.sleep(0.1)
    return sid


def test_unfinished_job_resumes_after_a_restart(tmp_path: Path) -> None:
    settings = settings_for(tmp_path, checkpoint_every=5)
    t0 = time.time()
    sid = _stopped_mid_training(settings)
    with TestClient(create_app(settings)) as client:
        details = set()
        body = client.get(f"/v1/scenes/{sid}").json()
        assert body["status"] in ("training", "baking", "ready")
        while body["status"] not in ("ready", "failed"):
            details.add(body["detail"])
            assert time.time() - t0 < 240
            time.sleep(0.05)
            body = client.get(f"/v1/scenes/{sid}").json()
        assert body["status"] == "ready"
        rec = client.app.state.services.store.get(sid)
    resumed = rec.stats["train"]["resumed_from_step"]
    assert resumed >= 10
    # the status says so while it trains
    assert f"training (fast preset, 40 steps, cpu), resumed from the checkpoint of step {resumed}" in details
    assert rec.attempts == 0  # a clean stop is not a lost worker


def time_builds(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """From now on each model build's seconds (the Trainer's construction), in the list returned."""
    import cmc.method.training

    builds: list[float] = []

    class TimedTrainer(cmc.method.training.Trainer):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            t = time.perf_counter()
            super().__init__(*args, **kwargs)
            builds.append(time.perf_counter() - t)

    monkeypatch.setattr(cmc.method.training, "Trainer", TimedTrainer)
    return builds


def test_unusable_checkpoint_trains_from_step_zero(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A stored checkpoint that cannot be loaded (here torn) is deleted and the job trains from step
    0; the model is built again for it, and the build time the job records (and paces its ETA by)
    is that build's alone."""
    settings = settings_for(tmp_path, checkpoint_every=5)
    sid = _stopped_mid_training(settings)
    checkpoint = tmp_path / "storage" / sid / "checkpoint.pt"
    checkpoint.write_bytes(checkpoint.read_bytes()[:1000])  # torn
    builds = time_builds(monkeypatch)
    with TestClient(create_app(settings)) as client:
        body = wait_for(client, sid, ("ready", "failed"))
        assert body["status"] == "ready", body
        rec = client.app.state.services.store.get(sid)
    assert rec.stats["train"]["resumed_from_step"] == 0
    assert len(builds) == 2  # one the checkpoint could not be loaded into, one trained from step 0
    assert rec.stats["train"]["build_seconds"] == pytest.approx(builds[1], abs=0.05)


def test_the_kernels_load_before_the_build_is_timed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A machine's first job compiles the numba kernels (tens of seconds on two cores): the job
    loads them before its model build, in a stage the status names, so that the build's time
    (whose pace predicts the steps' until one is measured) is not the compiler's. Here loading
    them takes a second longer than it does."""
    import cmc.kernel_cache

    warm_up = cmc.kernel_cache.warm_up_kernels

    def slow_warm_up() -> None:
        time.sleep(1.0)
        warm_up()

    monkeypatch.setattr(cmc.kernel_cache, "warm_up_kernels", slow_warm_up)
    builds = time_builds(monkeypatch)
    parts, _, _ = synthetic_upload(steps=4)
    t0 = time.time()
    with TestClient(create_app(settings_for(tmp_path, preview_at=""))) as client:
        r = client.post("/v1/scenes", files=parts)
        assert r.status_code == 202, r.text
        sid, details = r.json()["id"], []
        body = client.get(f"/v1/scenes/{sid}").json()
        while body["status"] not in ("ready", "failed"):
            details.append(body["detail"] or "")
            assert time.time() - t0 < 240
            time.sleep(0.05)
            body = client.get(f"/v1/scenes/{sid}").json()
        assert body["status"] == "ready", body
        rec = client.app.state.services.store.get(sid)
    loading = [i for i, d in enumerate(details) if d.startswith("loading the compiled kernels")]
    building = [i for i, d in enumerate(details) if d.startswith("building the model")]
    assert loading and building and loading[-1] < building[0], details
    assert rec.stats["train"]["kernels_seconds"] >= 1.0
    assert len(builds) == 1 and rec.stats["train"]["build_seconds"] == pytest.approx(builds[0], abs=0.05)


def test_previews_are_served_while_training_then_the_final_bake(tmp_path: Path) -> None:
    """A job bakes a preview after each share ``preview_at`` of its steps (at half the texel
    resolution), each in a folder of its own that replaces the last; render, depth and mpi answer
    from the latest (``Scene-Stage: preview``, its step in the status) while the scene trains, and
    at once after a restart mid-training (a crash between preview and final: the preview
    survives, the job resumes); once ready they answer from the final bake and no preview is left
    in storage."""
    parts, _, novel = synthetic_upload(steps=100)
    settings = settings_for(tmp_path, checkpoint_every=5, preview_at="0.2,0.4")
    gt_rgb, _ = render_layers(DEFAULT_LAYERS, novel)

    def render(client: TestClient, sid: str) -> tuple[str, float]:
        r = client.post(f"/v1/scenes/{sid}/render", json=render_body(novel))
        assert r.status_code == 200, r.text
        rgb = np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB"), dtype=np.float32) / 255
        return r.headers["scene-stage"], psnr(rgb, gt_rgb[0])

    def preview_files(sid: str) -> dict[str, int]:
        """Files in each preview folder of the scene in storage."""
        folders = (tmp_path / "storage" / sid).glob("preview*")
        return {p.name: sum(f.is_file() for f in p.rglob("*")) for p in folders}

    refused_before_preview = False
    with TestClient(create_app(settings)) as client:
        sid = client.post("/v1/scenes", files=parts).json()["id"]
        t0 = time.time()
        while not (body := client.get(f"/v1/scenes/{sid}").json())["preview_ready"]:
            assert body["status"] not in ("ready", "failed") and time.time() - t0 < 180, body
            assert body["preview_step"] is None
            if body["status"] == "training" and not refused_before_preview:
                r = client.post(f"/v1/scenes/{sid}/render", json=render_body(novel))
                if r.status_code == 409:  # else the preview came in between: then it must be served
                    assert r.json()["error"]["code"] == "scene_not_ready" and "no preview yet" in r.text
                    refused_before_preview = True
                else:
                    assert r.status_code == 200 and r.headers["scene-stage"] == "preview"
            time.sleep(0.05)
        assert body["status"] == "training" and body["progress"] < 1 and body["preview_step"] in (20, 40)
        stage, preview_psnr = render(client, sid)
        assert stage == "preview" and preview_psnr > 22.0  # the scene, not noise (untrained: 23.5 dB)
        depth = client.post(f"/v1/scenes/{sid}/depth", json=render_body(novel))
        assert depth.status_code == 200 and depth.headers["scene-stage"] == "preview"
        mpi = client.get(f"/v1/scenes/{sid}/mpi")
        assert mpi.status_code == 200 and mpi.headers["scene-stage"] == "preview"
        atlas, preview_tile = (json.loads(mpi.content)["mpis"][0][k] for k in ("atlas", "tile"))
        assert client.get(f"/v1/scenes/{sid}/mpi/{atlas}").headers["scene-stage"] == "preview"
        assert client.get(f"/v1/scenes/{sid}/camera-path?frames=3").status_code == 200
        assert client.get(f"/v1/scenes/{sid}/export.glb").status_code == 409  # final products wait
        while (body := client.get(f"/v1/scenes/{sid}").json())["preview_step"] != 40:  # the second replaces it
            assert body["status"] == "training" and body["preview_step"] == 20 and time.time() - t0 < 180, body
            time.sleep(0.05)
        assert render(client, sid)[0] == "preview"
        t1 = time.time()  # the first one is removed right after the record names the second
        while (files := preview_files(sid)).get("preview-20", 0) and time.time() - t1 < 10:
            time.sleep(0.05)
        assert files["preview-40"] > 0 and files.get("preview-20", 0) == 0, files
    assert refused_before_preview
    # the app stopped mid-training (checkpointed, as after a crash): the preview is served at once
    with TestClient(create_app(settings)) as client:
        body = client.get(f"/v1/scenes/{sid}").json()
        assert body["status"] in ("training", "baking") and body["preview_step"] == 40, body
        assert render(client, sid)[0] == "preview"
        body = wait_for(client, sid, ("ready", "failed"))
        assert body["status"] == "ready" and not body["preview_ready"] and body["preview_step"] is None, body
        stage, final_psnr = render(client, sid)
        assert stage == "final" and final_psnr > 25.0
        final_tile = client.get(f"/v1/scenes/{sid}/mpi").json()["mpis"][0]["tile"]
        assert preview_tile == [round(n * PREVIEW_TEXEL_SCALE) for n in final_tile]  # a quarter of the texels
        rec = client.app.state.services.store.get(sid)
    preview = rec.stats["preview"]
    assert preview["step"] == 40  # baked once more, not again on resuming
    assert preview["first_seconds_after_upload"] < preview["seconds_after_upload"]
    assert rec.stats["train"]["resumed_from_step"] >= 40
    assert not any(preview_files(sid).values())


class ServeProcess:
    """``cmc serve`` (embedded runner) as a child process on a free port."""

    def __init__(self, data_dir: Path):
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            self.url = f"http://127.0.0.1:{sock.getsockname()[1]}"
        root = Path(__file__).resolve().parents[1]
        env = {**os.environ, "PYTHONPATH": str(root), "CMC_DEVICE": "cpu", "CMC_HEARTBEAT_SECONDS": "0.2"}
        args = [sys.executable, "-m", "cmc.cli", "serve", "--log-level", "warning", "--data-dir", str(data_dir)]
        self.log = data_dir.parent / f"{data_dir.name}.log"
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen([*args, "--port", self.url.rsplit(":", 1)[1]], env=env, stdout=log, stderr=log)
        self.wait(lambda: httpx2.get(f"{self.url}/healthz").status_code == 200, "start")

    def wait(self, ready, what: str, timeout: float = 240):
        t0 = time.time()
        while time.time() - t0 < timeout:
            assert self.proc.poll() is None, f"cmc serve exited:\n{self.log.read_text()[-3000:]}"
            try:
                if result := ready():
                    return result
            except httpx2.HTTPError:
                pass
            time.sleep(0.2)
        raise AssertionError(f"cmc serve: no {what} after {timeout} s:\n{self.log.read_text()[-3000:]}")

    def status(self, scene_id: str) -> dict:
        return httpx2.get(f"{self.url}/v1/scenes/{scene_id}").json()

    def terminate(self) -> None:
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(60)


def test_sigterm_after_pose_estimation_checkpoints_and_resumes(tmp_path: Path) -> None:
    """SfM loads pycolmap, whose logging library takes over SIGTERM when imported; a later
    stop must still checkpoint the training job (the preset's 250-step period is never reached)."""
    import torch

    from service.db.scenes import SceneStore

    data = tmp_path / "data"
    server = ServeProcess(data)
    try:
        grey = [("images", (f"IMG_{i}.png", png(np.full((72, 96, 3), 0.4)), "image/png")) for i in range(3)]
        sfm = httpx2.post(f"{server.url}/v1/scenes", files=grey).json()["id"]  # no cameras: runs SfM
        assert server.wait(lambda: server.status(sfm)["status"] == "failed", "pose estimation")
        parts, _, _ = synthetic_upload(steps=5000)
        sid = httpx2.post(f"{server.url}/v1/scenes", files=parts).json()["id"]
        server.wait(lambda: server.status(sid)["status"] == "training" and server.status(sid)["progress"] > 0, "steps")
    finally:
        server.terminate()  # uvicorn stops gracefully, then exits by re-raising the signal
    ckpt = data / "storage" / sid / "checkpoint.pt"
    assert ckpt.exists(), f"no checkpoint at shutdown:\n{server.log.read_text()[-3000:]}"
    step = torch.load(ckpt, weights_only=False)["step"]
    assert 0 < step < 250
    server = ServeProcess(data)
    try:
        store = SceneStore(f"sqlite:///{data.resolve() / 'cmc.db'}")
        resumed = server.wait(lambda: store.get(sid).stats.get("train", {}).get("resumed_from_step"), "resume")
        store.close()
    finally:
        server.terminate()
    assert resumed == step


def test_serve_refuses_open_network_without_keys_and_new_api_key(tmp_path: Path, capsys, monkeypatch) -> None:
    from cmc.cli import main
    from service.auth import KeyRing

    monkeypatch.delenv("CMC_API_KEYS", raising=False)
    monkeypatch.delenv("CMC_API_KEYS_FILE", raising=False)
    assert main(["serve", "--host", "0.0.0.0", "--data-dir", str(tmp_path / "d")]) == 2
    assert "without API keys" in capsys.readouterr().err
    keys = tmp_path / "keys.txt"
    assert main(["new-api-key", str(keys), "--label", "ios app"]) == 0
    key = capsys.readouterr().out.splitlines()[0]
    assert key.startswith("cmc_") and key not in keys.read_text()
    ring = KeyRing.load("", keys)
    assert ring.owner(f"Bearer {key}") == key_digest(key)[:16]
    assert (keys.stat().st_mode & 0o777) == 0o600
