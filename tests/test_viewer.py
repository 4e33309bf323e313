"""The WebGL2 viewer (service/static/viewer.html) in a real headless Chromium.

Chromium is Debian's (``apt-get install -y chromium``), driven by Playwright for Python with
``executable_path`` (no browser download). Headless Chromium gives WebGL2 through ANGLE on
SwiftShader (software Vulkan), which ``--use-angle=swiftshader --enable-unsafe-swiftshader``
asks for explicitly. Only 127.0.0.1 is contacted. Without Chromium or Playwright the tests skip,
unless the environment variable CI is set (then they fail: CI must install both).
"""

from __future__ import annotations

import functools
import io
import json
import shutil
import threading
from dataclasses import replace
from http.server import BaseHTTPRequestHandler, SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cmc.config import preset_config
from cmc.data.datasets import synthetic_cameras, synthetic_scene
from cmc.eval.diagnostics import depth_preview
from cmc.eval.metrics import psnr
from cmc.geometry.camera_paths import mean_pose
from cmc.method.training import Trainer
from cmc.serving.baking import PREVIEW_TEXEL_SCALE, BakedScene, bake

VIEWER = Path(__file__).resolve().parent.parent / "service" / "static" / "viewer.html"
W, H = 80, 60


@pytest.fixture(scope="module", autouse=True)
def _browser_first(browser):
    """Skip (or fail under CI) before building the scene when there is no browser."""


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A folder with viewer.html and a baked tiny synthetic scene in baked/, and two previews of
    its planes (preview/ all white, preview30/ all black)."""
    root = tmp_path_factory.mktemp("site")
    scene = synthetic_scene(num_views=3, width=W, height=H)
    cfg = preset_config("fast", steps=10, rays_per_view=256, unseen_rays=256)
    cfg = replace(cfg, model=replace(cfg.model, num_planes=12))
    trainer = Trainer(scene, cfg)
    trainer.fit()
    bake(trainer.model, root / "baked")
    for folder, colour in (("preview", 255), ("preview30", 0)):
        bake(trainer.model, root / folder, scale=PREVIEW_TEXEL_SCALE)  # as a job bakes its previews
        for atlas in (root / folder).glob("*.png"):  # the same planes, of one colour
            rgba = np.asarray(Image.open(atlas)).copy()
            rgba[..., :3] = colour
            Image.fromarray(rgba, "RGBA").save(atlas)
    shutil.copy(VIEWER, root / "viewer.html")
    return root


def _serve(handler) -> tuple[ThreadingHTTPServer, str]:
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_port}"


class _Quiet(SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture(scope="module")
def static_url(site):
    server, url = _serve(functools.partial(_Quiet, directory=str(site)))
    yield url
    server.shutdown()


@pytest.fixture()
def page(browser):
    ctx = browser.new_context(viewport={"width": 900, "height": 700}, device_scale_factor=1)
    pg = ctx.new_page()
    pg.set_default_timeout(60_000)
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    yield pg
    ctx.close()
    assert not errors, errors


def _wait_ready(pg) -> None:
    result = pg.evaluate("() => window.cmcViewer.ready.then(() => 'ready', e => 'error: ' + e.message)")
    assert result == "ready"


def _frame(pg, after: int) -> np.ndarray:
    """Wait until frame number ``after`` is drawn, then screenshot the canvas: [H, W, 3] in [0, 1]."""
    pg.wait_for_function("n => window.cmcViewer.frames >= n", arg=after)
    png = pg.locator("#view").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64) / 255


def _quantised(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0, 1) * 255) / 255


def test_viewer_matches_the_server_renderer(site, static_url, page, record_property):
    """A novel camera between input views 0 and 1: colour and depth view against BakedScene.render."""
    page.goto(f"{static_url}/viewer.html?mpi=baked/")
    _wait_ready(page)
    cam = synthetic_cameras(5, W, H)[1]
    K, pose = cam.K[0], cam.world_from_cam[0]
    n = page.evaluate("([K, P, w, h]) => window.cmcViewer.setCamera(K, P, w, h)", [K.tolist(), pose.tolist(), W, H])
    shot = _frame(page, n)
    assert shot.shape == (H, W, 3)
    baked = BakedScene.load(site / "baked")
    ref = baked.render(K, pose)
    score = psnr(shot, _quantised(ref.rgb))
    record_property("viewer_psnr_db", score)
    print(f"viewer vs server PSNR: {score:.1f} dB")
    assert score >= 30
    n = page.evaluate("() => { window.cmcViewer.setDepthView(true); return window.cmcViewer.frames + 1; }")
    depth_shot = _frame(page, n)
    depth_ref = depth_preview(ref.depth, baked.near, baked.far)
    assert psnr(depth_shot, _quantised(depth_ref)) >= 30


def test_drag_moves_the_camera(site, static_url, page):
    page.goto(f"{static_url}/viewer.html?mpi=baked/mpi.json")
    _wait_ready(page)
    before = _frame(page, 1)
    start = page.evaluate("() => window.cmcViewer.getCamera()")
    pose0 = np.array(start["world_from_cam"])
    # The start view is the mean input camera (cmc.geometry.camera_paths.mean_pose) with view 0's intrinsics,
    # scaled to the canvas: the 900x700 window fits 900x675 at the photos' 4:3, which renders at
    # twice the photos' size (the most it upscales).
    baked = BakedScene.load(site / "baked")
    refs = np.stack([f.world_from_ref.numpy().astype(np.float64) for f in baked.frames])
    assert np.allclose(pose0, mean_pose(refs), atol=1e-6)
    assert (start["width"], start["height"]) == (2 * W, 2 * H)
    assert np.allclose(start["K"], np.diag([2, 2, 1]) @ baked.frames[0].K.numpy(), atol=1e-4)
    frames = page.evaluate("() => window.cmcViewer.frames")
    box = page.locator("#view").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 200, y + 60, steps=5)
    page.mouse.up()
    after = _frame(page, frames + 1)
    pose1 = np.array(page.evaluate("() => window.cmcViewer.getCamera().world_from_cam"))
    assert np.linalg.norm(pose1[:3, 3] - pose0[:3, 3]) > 1e-3  # the camera moved ...
    assert np.abs(after - before).mean() > 0.01  # ... and so did the picture
    page.click("#reset-btn")  # back to the start view
    assert np.allclose(page.evaluate("() => window.cmcViewer.getCamera().world_from_cam"), pose0)


def test_the_canvas_fills_the_window_at_the_photos_aspect(site, static_url, browser):
    """A 1280x800 window shows the 4:3 scene 1067x800 (not at the photos' 80x60), renders it at
    most twice the photos' size, follows a resize, and an exact camera is shown pixel for pixel."""
    ctx = browser.new_context(viewport={"width": 1280, "height": 800}, device_scale_factor=1)
    try:
        pg = ctx.new_page()
        pg.goto(f"{static_url}/viewer.html?mpi=baked/")
        _wait_ready(pg)
        box = pg.locator("#view").bounding_box()
        assert abs(box["width"] - 800 * 4 / 3) < 1 and abs(box["height"] - 800) < 1
        assert box["x"] > 100  # centred
        cam = pg.evaluate("() => window.cmcViewer.getCamera()")
        assert (cam["width"], cam["height"]) == (2 * W, 2 * H)
        pg.set_viewport_size({"width": 600, "height": 800})
        pg.wait_for_function("() => document.getElementById('view').getBoundingClientRect().width < 601")
        box = pg.locator("#view").bounding_box()
        assert abs(box["width"] - 600) < 1 and abs(box["height"] - 450) < 1
        pose = pg.evaluate("() => window.cmcViewer.getCamera().world_from_cam")
        pg.evaluate("(P) => window.cmcViewer.setCamera(null, P, 40, 30)", pose)
        box = pg.locator("#view").bounding_box()
        assert (round(box["width"]), round(box["height"])) == (40, 30)
    finally:
        ctx.close()


class _FakeAPI(BaseHTTPRequestHandler):
    """The two routes the viewer uses: GET /v1/scenes/{id} and /v1/scenes/{id}/mpi/{file}.

    Scene "s1" trains for its first two status requests, then is ready; "bad" has failed; "p1"
    trains with a preview (``site/preview``, the scene baked at half resolution, all white) for its first
    three status requests, then is ready (``site/baked``). Requests without the bearer key get
    401. The class attributes are set per test.
    """

    site: Path
    key = "k-123"
    polls = 0
    auth_seen: list = []

    def log_message(self, *args):
        pass

    def _send(self, code: int, body: bytes, ctype: str) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self):  # noqa: N802
        if self.path.split("?")[0] == "/viewer.html":
            return self._send(200, (self.site / "viewer.html").read_bytes(), "text/html")
        type(self).auth_seen.append(self.headers.get("Authorization"))
        if self.headers.get("Authorization") != f"Bearer {self.key}":
            return self._send(401, b'{"error": {"code": "unauthorized", "message": "bad key"}}', "application/json")
        if self.path == "/v1/scenes/s1":
            type(self).polls += 1
            ready = self.polls > 2
            status = {
                "id": "s1",
                "status": "ready" if ready else "training",
                "progress": 1.0 if ready else 0.4,
                "eta_seconds": None if ready else 95.0,
                "error": None,
            }
            return self._send(200, json.dumps(status).encode(), "application/json")
        if self.path == "/v1/scenes/p1":
            type(self).polls += 1
            ready = self.polls > 3
            status = {
                "id": "p1",
                "status": "ready" if ready else "training",
                "preview_ready": not ready,
                "preview_step": None if ready else 0 if self.polls == 1 else 30,
                "progress": 1.0 if ready else 0.5,
                "eta_seconds": 0.0 if ready else 30.0,
                "error": None,
            }
            return self._send(200, json.dumps(status).encode(), "application/json")
        if self.path == "/v1/scenes/bad":
            status = {
                "id": "bad",
                "status": "failed",
                "progress": 0.1,
                "eta_seconds": None,
                "error": {"code": "poses_failed", "message": "only 1 of 3 photos registered"},
            }
            return self._send(200, json.dumps(status).encode(), "application/json")
        scene, _, name = self.path.removeprefix("/v1/scenes/").partition("/mpi/")
        if scene in ("s1", "p1") and name and "/" not in name:
            folder = "baked"
            if scene == "p1" and self.polls <= 3:
                folder = "preview" if self.polls == 1 else "preview30"
            f = self.site / folder / name
            if f.is_file():
                return self._send(200, f.read_bytes(), "application/json" if f.suffix == ".json" else "image/png")
        return self._send(404, b'{"error": {"code": "not_found", "message": "no such thing"}}', "application/json")


@pytest.fixture()
def api_url(site):
    handler = type("API", (_FakeAPI,), {"site": site, "polls": 0, "auth_seen": []})
    server, url = _serve(handler)
    yield url, handler
    server.shutdown()


def test_api_mode_shows_training_progress_then_the_scene(api_url, page):
    url, api = api_url
    page.goto(f"{url}/viewer.html?scene=s1#key={api.key}")
    page.wait_for_function("() => document.getElementById('status-text').textContent.includes('Training')")
    assert "40%" in page.text_content("#status-text")
    assert "min left" in page.text_content("#status-eta")
    _wait_ready(page)
    assert page.is_hidden("#status")
    assert _frame(page, 1).std() > 0.05  # a picture, not a blank canvas
    assert api.polls == 3 and set(api.auth_seen) == {f"Bearer {api.key}"}  # every request carried the key


def test_api_mode_shows_a_preview_then_swaps_in_the_final_scene(api_url, page):
    """A scene whose job published a preview is shown at once, marked as a preview; a later
    preview (the status' preview_step changed) replaces it, and when the scene is ready the
    viewer loads the final bake in its place, each from the same camera."""
    url, api = api_url
    page.goto(f"{url}/viewer.html?scene=p1#key={api.key}")
    _wait_ready(page)
    assert page.evaluate("() => [window.cmcViewer.stage, window.cmcViewer.previewStep]") == ["preview", 0]
    assert "Preview" in page.text_content("#stage-note") and page.is_hidden("#status")
    pose = page.evaluate("() => window.cmcViewer.getCamera().world_from_cam")
    preview = _frame(page, page.evaluate("() => window.cmcViewer.frames"))
    page.wait_for_function("() => window.cmcViewer.previewStep === 30", timeout=30_000)
    later = _frame(page, page.evaluate("() => window.cmcViewer.frames"))
    assert page.evaluate("() => window.cmcViewer.stage") == "preview"
    page.wait_for_function("() => window.cmcViewer.stage === 'final'", timeout=30_000)
    final = _frame(page, page.evaluate("() => window.cmcViewer.frames"))
    assert page.is_hidden("#stage-note")
    assert page.evaluate("() => window.cmcViewer.getCamera().world_from_cam") == pose
    # the first preview's planes are white, the second's black: the final picture is the scene's own colours
    assert preview.mean() > 0.9 and later.mean() < 0.1 and 0.1 < final.mean() < preview.mean() - 0.2


def test_api_mode_reports_a_failed_scene(api_url, page):
    url, api = api_url
    page.goto(f"{url}/viewer.html?scene=bad#key={api.key}")
    result = page.evaluate("() => window.cmcViewer.ready.then(() => 'ready', e => e.message)")
    assert "only 1 of 3 photos registered" in result
    assert "only 1 of 3 photos registered" in page.text_content("#status-text")


def test_unseen_view_tints_what_no_photo_saw(site, static_url, page):
    """A camera turned 20 degrees sideways sees past the inputs: the pixels the viewer tints are
    those BakedScene.coverage marks unseen (what ?coverage=true leaves transparent)."""
    page.goto(f"{static_url}/viewer.html?mpi=baked/")
    _wait_ready(page)
    cam = synthetic_cameras(5, W, H)[1]
    K, pose = cam.K[0], cam.world_from_cam[0].copy()
    a = np.radians(20)
    pose[:3, :3] = pose[:3, :3] @ np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    n = page.evaluate("([K, P, w, h]) => window.cmcViewer.setCamera(K, P, w, h)", [K.tolist(), pose.tolist(), W, H])
    plain = _frame(page, n)
    n = page.evaluate("() => { window.cmcViewer.setUnseenView(true); return window.cmcViewer.frames + 1; }")
    tinted = _frame(page, n)
    marked = np.abs(tinted - plain).sum(-1) > 0.05
    baked = BakedScene.load(site / "baked")
    unseen = ~baked.coverage(K, pose, baked.render(K, pose).depth)
    assert 0.1 < unseen.mean() < 0.9, unseen.mean()  # the camera sees both
    assert (marked == unseen).mean() >= 0.97, (marked.mean(), unseen.mean(), (marked == unseen).mean())
