"""Small builders shared by the tests: poses, synthetic scene uploads for the service, and where the
shared data lies (``$CMC_SHARED_DIR``, else ``../shared`` beside the checkout)."""

from __future__ import annotations

import importlib.util
import io
import json
import math
import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cmc.data.datasets import Scene, synthetic_cameras, synthetic_scene
from cmc.geometry.cameras import CameraFile, Cameras, camera_file_to_dict

S3_CREDENTIALS = {"AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1"}
SHARED_DIR = Path(os.environ.get("CMC_SHARED_DIR") or Path(__file__).resolve().parents[1].parent / "shared")
REDIS_URL = os.environ.get("CMC_TEST_REDIS", "redis://127.0.0.1:6379/14")  # the real Redis of the tests
PG_ADMIN = os.environ.get("CMC_TEST_POSTGRES", "postgresql://postgres@127.0.0.1:5432/postgres")  # the real PostgreSQL


@contextmanager
def throwaway_postgres(prefix: str = "cmc_test_") -> Iterator[str]:
    """A new, empty database on the real PostgreSQL (``PG_ADMIN``); yields its SQLAlchemy URL and
    drops it afterwards. Skips the test when the server cannot be reached (fails under CI)."""
    psycopg = pytest.importorskip("psycopg")
    name = f"{prefix}{uuid.uuid4().hex[:12]}"
    try:
        admin = psycopg.connect(PG_ADMIN, autocommit=True, connect_timeout=3)
    except psycopg.OperationalError as e:
        if os.environ.get("CI"):
            raise
        pytest.skip(f"no PostgreSQL at {PG_ADMIN}: {e}")
    admin.execute(f'CREATE DATABASE "{name}"')
    try:
        yield PG_ADMIN.replace("postgresql://", "postgresql+psycopg://").rsplit("/", 1)[0] + f"/{name}"
    finally:
        admin.execute(f'DROP DATABASE "{name}" WITH (FORCE)')
        admin.close()


def finished_job(store, options: dict, stats: dict, has_cameras: bool = False) -> str:
    """A record in scene store ``store`` taken through both phases to ``ready`` with ``stats``;
    its id."""
    rec, _ = store.create("o", options, ["a.jpg"], ["00.jpg"], has_cameras)
    assert store.claim(rec.id, "poses", "w", 30) and store.advance(rec.id, "w", "train", "training")
    assert store.claim(rec.id, "train", "w", 30) and store.advance(rec.id, "w", "done", "ready", stats=stats)
    return rec.id


def rotation(axis, angle: float) -> np.ndarray:
    """[3, 3] rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * Kx + (1 - math.cos(angle)) * Kx @ Kx


def apply_homography(H, uv, eps: float = 1e-6):
    """Map pixel coordinates through homographies (torch tensors; the renderers use the affine
    form of the plane-induced homography, cmc.mpi.rendering.render_ray_groups).

    Shape:
        H: [..., D, 3, 3]; uv: [..., R, 2] continuous pixel coordinates.
        Returns uv' [..., R, D, 2] and valid [..., R, D] (the point lies in front, w > eps).
    """
    import torch

    ones = torch.ones_like(uv[..., :1])
    p = torch.cat([uv, ones], dim=-1)  # [..., R, 3]
    q = torch.einsum("...dij,...rj->...rdi", H, p)
    w = q[..., 2]
    valid = w > eps
    w = torch.where(valid, w, torch.full_like(w, eps))
    return q[..., :2] / w[..., None], valid


def rigid(R: np.ndarray, t) -> np.ndarray:
    """[4, 4] rigid transform with rotation R and translation t."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def synthetic_upload(
    num_views: int = 3, width: int = 96, height: int = 72, with_cameras: bool = True, steps: int = 8
) -> tuple[list[tuple], Scene, Cameras]:
    """A tiny synthetic scene (known poses and depths) as the multipart parts of
    ``POST /v1/scenes``: PNG photos named ``view<i>.png``, its cameras file (OpenGL convention,
    with near/far) and options. Returns (parts for httpx2 ``files=``, the scene, a novel camera
    halfway between input views 0 and 1 for checking renders against the exact ground truth)."""
    scene = synthetic_scene(num_views, width, height)
    parts: list[tuple] = []
    for i, img in enumerate(scene.images):
        buf = io.BytesIO()
        Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).save(buf, "PNG")
        parts.append(("images", (f"view{i}.png", buf.getvalue(), "image/png")))
    if with_cameras:
        names = [f"view{i}.png" for i in range(num_views)]
        cams = camera_file_to_dict(CameraFile(scene.cameras, names, scene.near_far), "opengl")
        parts.append(("cameras", ("cameras.json", json.dumps(cams).encode(), "application/json")))
    parts.append(("options", (None, json.dumps({"steps": steps, "resolution": max(width, height)}))))
    novel = synthetic_cameras(2 * num_views - 1, width, height)[1:2]
    return parts, scene, novel


def render_body(cameras: Cameras, convention: str = "opengl") -> dict:
    """The JSON body of the render / depth endpoints for the first of ``cameras``: its frame of
    the cameras file plus the image size and convention (what a client sends)."""
    data = camera_file_to_dict(CameraFile(cameras[:1], ["render"]), convention)
    frame = {k: v for k, v in data["frames"][0].items() if k != "file_path"}
    return {**frame, "w": data["w"], "h": data["h"], "convention": convention}


# Headless Chromium of the browser tests (the `browser` fixture in conftest.py).
CHROMIUM_ARGS = [
    "--no-sandbox",  # runs as root in containers
    "--use-angle=swiftshader",  # WebGL2 on the CPU (ANGLE -> SwiftShader Vulkan)
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",  # the machine has no network: no update, sync or
    "--disable-component-update",  # safe-browsing requests at all
    "--disable-sync",
    "--no-first-run",
    "--disable-default-apps",
]


def browser_unavailable(message: str):
    """Skip a browser test for ``message``; under CI (where the browser must be there) fail."""
    if os.environ.get("CI", "").lower() not in ("", "0", "false"):
        pytest.fail(f"{message} (CI is set: the browser tests must run)")
    pytest.skip(message)


def _bench_servers():
    """bench/servers.py, the benchmarks' server helpers (a script folder, not a package)."""
    spec = importlib.util.spec_from_file_location(
        "bench_servers", Path(__file__).resolve().parents[1] / "bench/servers.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


free_port = _bench_servers().free_port  # a free port below the ephemeral range, as the benchmarks take one


def new_bucket(endpoint: str) -> str:
    """A fresh bucket at the S3 endpoint (the ``s3`` fixture's moto server)."""
    import boto3

    name = f"cmc-{uuid.uuid4().hex[:12]}"
    boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1").create_bucket(Bucket=name)
    return name
