"""The exported .glb in a real glTF viewer: three.js (installed from npm at test time into
``.three/``, kept between runs) in headless Chromium, as in tests/test_viewer.py. Its screenshot
through the file's own glTF camera, and through a novel camera, is compared with the server's
renderer (``BakedScene.render``) of the exported MPI at the same camera.

The renderer's blend of all MPIs is not the reference: the file holds one MPI, and the test
measures the export (geometry, textures, cameras, blending order), not the choice of MPI.
Without Chromium, Playwright, npm or the npm registry the test skips, unless CI is set.
"""

from __future__ import annotations

import functools
import io
import json
import math
import shutil
import subprocess
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pytest
from helpers import browser_unavailable
from PIL import Image

from cmc.config import preset_config
from cmc.data.datasets import synthetic_cameras, synthetic_scene
from cmc.eval.metrics import psnr
from cmc.geometry.cameras import convert_pose
from cmc.method.training import Trainer
from cmc.serving.baking import BakedScene, bake
from cmc.serving.gltf import export_glb, scene_root

ROOT = Path(__file__).resolve().parents[1]
THREE_VERSION = "0.187.0"
THREE_DIR = ROOT / ".three"  # npm's install of three, kept between runs (ignored by git)
W, H = 80, 60

PAGE = """<!doctype html>
<html><head><link rel="icon" href="data:,"></head><body style="margin:0;background:#000">
<script type="importmap">
{"imports": {"three": "./three/build/three.module.js", "three/addons/": "./three/examples/jsm/"}}
</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
const q = JSON.parse(decodeURIComponent(location.hash.slice(1)));
const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
renderer.setSize(q.w, q.h);
renderer.setClearColor(0x000000, 1);
document.body.appendChild(renderer.domElement);
window.done = new GLTFLoader().loadAsync('scene.glb').then((gltf) => {
  let cam;
  if (q.camera !== undefined) {
    cam = gltf.cameras[q.camera];  // the file's own camera, placed by the node tree
  } else {
    cam = new THREE.PerspectiveCamera(q.fov, q.w / q.h, q.near, q.far);
    new THREE.Matrix4().fromArray(q.matrix).decompose(cam.position, cam.quaternion, cam.scale);
  }
  gltf.scene.updateMatrixWorld(true);
  renderer.render(gltf.scene, cam);
  return gltf.cameras.length;
});
</script></body></html>
"""


@pytest.fixture(scope="module")
def three() -> Path:
    """three.js from the npm registry (the files the page imports)."""
    module = THREE_DIR / "node_modules" / "three"
    if (
        not (module / "package.json").exists()
        or json.loads((module / "package.json").read_text())["version"] != THREE_VERSION
    ):
        npm = shutil.which("npm")
        if npm is None:
            browser_unavailable("npm is not installed (apt-get install -y npm)")
        THREE_DIR.mkdir(exist_ok=True)
        cmd = [npm, "install", "--prefix", str(THREE_DIR), f"three@{THREE_VERSION}", "--no-audit", "--no-fund"]
        done = subprocess.run(cmd + ["--ignore-scripts"], capture_output=True, text=True, timeout=300)
        if done.returncode != 0:
            browser_unavailable(f"npm install three failed: {done.stderr[-500:]}")
    return module


@pytest.fixture(scope="module")
def site(tmp_path_factory, three, browser):
    """A folder served on 127.0.0.1: the page, three.js and the .glb of a tiny trained scene."""
    root = tmp_path_factory.mktemp("gltf-site")
    scene = synthetic_scene(num_views=3, width=W, height=H)
    trainer = Trainer(scene, preset_config("fast", steps=10, rays_per_view=256, unseen_rays=256))
    trainer.fit()
    bake(trainer.model, root / "baked")
    data, index = export_glb(root / "baked")
    (root / "scene.glb").write_bytes(data)
    (root / "index.html").write_text(PAGE)
    (root / "three").symlink_to(three, target_is_directory=True)

    class Quiet(SimpleHTTPRequestHandler):
        def log_message(self, *args: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(root)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield root, f"http://127.0.0.1:{server.server_port}", index
    server.shutdown()


def screenshot(browser, url: str, query: dict) -> np.ndarray:
    ctx = browser.new_context(viewport={"width": 200, "height": 200}, device_scale_factor=1)
    page = ctx.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    try:
        page.goto(f"{url}/index.html#{quote(json.dumps(query))}")
        assert page.evaluate("() => window.done") == 3, "three.js did not find the three cameras"
        png = page.locator("canvas").screenshot()
    finally:
        ctx.close()
    assert not errors, errors
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64) / 255


def reference(baked: BakedScene, K: np.ndarray, pose: np.ndarray, index: int) -> np.ndarray:
    rgb = baked.render(K, pose, W, H, mpi_index=index).rgb
    return np.round(np.clip(rgb, 0, 1) * 255) / 255


def test_three_js_renders_the_glb_as_the_server_does(site, browser, record_property) -> None:
    root, url, index = site
    baked = BakedScene.load(root / "baked")
    frame = baked.frames[index]
    K, pose = frame.K.numpy().astype(np.float64), frame.world_from_ref.numpy().astype(np.float64)
    # 1. the file's own camera of the exported MPI's view (glTF camera, node tree, root)
    shot = screenshot(browser, url, {"w": W, "h": H, "camera": index})
    assert shot.shape == (H, W, 3) and shot.std() > 0.05
    own = psnr(shot, reference(baked, K, pose, index))
    # 2. a novel camera between input views 0 and 1, given to three.js in the file's frame
    novel = synthetic_cameras(5, W, H)[1]
    matrix = scene_root(json.loads((root / "baked" / "mpi.json").read_text())) @ convert_pose(
        novel.world_from_cam[0], "opencv", "opengl"
    )
    fov = math.degrees(2 * math.atan(H / (2 * novel.K[0, 1, 1])))
    query = {"w": W, "h": H, "fov": fov, "near": 0.1, "far": 100, "matrix": matrix.T.reshape(-1).tolist()}
    shot_novel = screenshot(browser, url, query)
    moved = psnr(shot_novel, reference(baked, novel.K[0], novel.world_from_cam[0], index))
    record_property("gltf_psnr_db", {"own_camera": own, "novel_camera": moved})
    print(f"three.js vs server renderer: {own:.1f} dB at the file's camera, {moved:.1f} dB at a novel one")
    assert own >= 30 and moved >= 30
    assert psnr(shot, shot_novel) < own  # the two cameras do see different pictures
