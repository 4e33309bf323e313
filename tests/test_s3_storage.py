"""Artifact storage on S3, against a real S3 HTTP endpoint: moto's standalone server (an
emulator; docker-compose runs MinIO), started as a subprocess by the ``s3`` fixture (conftest.py).

The storage contract runs on both backends (LocalStorage and S3Storage); then S3 alone: a writer
killed with SIGKILL in the middle of a checkpoint's multipart upload leaves the previous
checkpoint readable, presigned URLs download the stored bytes, bad settings fail with a readable
error, and a job runs end to end through the embedded service with S3 storage (the render cache
loading the baked scene from the bucket, downloads redirected to presigned URLs).
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient
from helpers import free_port, new_bucket, render_body, synthetic_upload
from PIL import Image
from pydantic import ValidationError

from service.app import create_app
from service.settings import load_settings
from service.storage import LocalStorage, Storage, StorageError, open_storage
from service.storage.s3 import S3Storage

ROOT = Path(__file__).resolve().parents[1]
SCENE = "0123456789abcdef0123456789abcdef"


@pytest.fixture(params=["local", "s3"])
def storage(request, tmp_path: Path) -> Storage:
    if request.param == "local":
        return LocalStorage(tmp_path / "storage")
    endpoint = request.getfixturevalue("s3")
    return S3Storage(new_bucket(endpoint), "cmc", tmp_path / "work", endpoint)


# -- the contract, on both backends --------------------------------------------------------------


def test_storage_contract(storage: Storage, tmp_path: Path) -> None:
    key = f"{SCENE}/uploads/cameras.json"
    assert not storage.exists(key) and storage.list(SCENE) == []
    with pytest.raises(StorageError):
        storage.read_bytes(key)
    storage.write_bytes(key, b"one")
    storage.write_bytes(key, b"two")
    assert storage.exists(key) and storage.read_bytes(key) == b"two"
    for bad in ("../etc/passwd", f"{SCENE}/../x", "not-a-scene/x", f"{SCENE}/a b"):
        with pytest.raises(StorageError):
            storage.write_bytes(bad, b"x")
        assert not storage.exists(bad)

    # a file published from a local path; reading it back as a local copy
    src = tmp_path / "ckpt"
    src.write_bytes(b"weights")
    storage.publish(f"{SCENE}/checkpoint.pt", src)
    with storage.reading(f"{SCENE}/checkpoint.pt") as p:
        assert p.read_bytes() == b"weights"
    with storage.reading(f"{SCENE}/nothing.pt") as p:
        assert not p.exists()

    # folders: written in place, published whole, replacing the old one (its stale files too)
    with storage.writing(f"{SCENE}/baked", manifest="mpi.json") as folder:
        assert not folder.exists() and folder.parent.is_dir()
        (folder / "sub").mkdir(parents=True)
        for name in ("a.png", "sub/b.png", "old.png", "mpi.json"):
            (folder / name).write_bytes(name.encode())
    with storage.writing(f"{SCENE}/baked", manifest="mpi.json") as folder:
        (folder / "sub").mkdir(parents=True)
        for name in ("a.png", "sub/b.png", "mpi.json"):
            (folder / name).write_bytes(b"new " + name.encode())
    baked = [f"{SCENE}/baked/{n}" for n in ("a.png", "mpi.json", "sub/b.png")]
    assert storage.list(f"{SCENE}/baked") == baked
    with storage.reading(f"{SCENE}/baked") as folder:
        assert sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()) == [
            "a.png",
            "mpi.json",
            "sub/b.png",
        ]
        assert (folder / "sub" / "b.png").read_bytes() == b"new sub/b.png"

    # a with block that fails publishes nothing
    with pytest.raises(RuntimeError), storage.writing(f"{SCENE}/videos/orbit.mp4") as out:
        out.write_bytes(b"half a video")
        raise RuntimeError("ffmpeg died")
    assert not storage.exists(f"{SCENE}/videos/orbit.mp4")

    storage.delete(f"{SCENE}/checkpoint.pt")
    storage.delete(f"{SCENE}/checkpoint.pt")  # no error when it is gone
    assert not storage.exists(f"{SCENE}/checkpoint.pt")
    assert storage.list(SCENE) == sorted([key, *baked])
    storage.delete_scene(SCENE)
    storage.delete_scene(SCENE)
    assert storage.list(SCENE) == [] and not storage.exists(key)
    storage.check()
    with storage.scratch() as a, storage.scratch() as b:
        assert a != b and a.is_dir() and list(a.iterdir()) == []
        (a / "checkpoint.pt").write_bytes(b"left by a killed worker")
        os.utime(a, (time.time() - 7200, time.time() - 7200))
        assert storage.sweep_scratch(3600) == [a] and b.is_dir()
    assert not a.exists() and not b.exists()


def test_folder_manifest_is_published_last(storage: Storage, tmp_path: Path) -> None:
    """A reader that sees the manifest sees every file it names, in the old and the new version;
    on S3 the manifest is also the last object written."""
    names = [f"mpi_{i:02d}.png" for i in range(6)]
    key = f"{SCENE}/baked"

    def folder(version: int) -> Path:
        f = tmp_path / f"v{version}"
        f.mkdir()
        for n in names:
            f.joinpath(n).write_bytes(bytes([version]) * 300_000)
        f.joinpath("mpi.json").write_text(json.dumps({"version": version}))
        return f

    storage.publish(key, folder(1), manifest="mpi.json")
    written: list[str] = []
    if isinstance(storage, S3Storage):
        storage.client.meta.events.register(
            "before-parameter-build.s3.PutObject", lambda params, **kw: written.append(params["Key"].rsplit("/", 1)[-1])
        )
    seen, done = [], threading.Event()

    def reader() -> None:
        while not done.is_set():
            try:
                version = json.loads(storage.read_bytes(f"{key}/mpi.json"))["version"]
                files = [storage.read_bytes(f"{key}/{n}")[:1] for n in names]
            except StorageError:
                continue  # between the old manifest and the new one
            seen.append((version, files))

    def wait_until(cond) -> None:
        t0 = time.time()
        while not cond():
            assert time.time() - t0 < 30, "the reader saw nothing"
            time.sleep(0.01)

    t = threading.Thread(target=reader)
    t.start()
    try:
        wait_until(lambda: seen)
        storage.publish(key, folder(2), manifest="mpi.json")
        wait_until(lambda: seen[-1][0] == 2)
    finally:
        done.set()
        t.join()
    assert json.loads(storage.read_bytes(f"{key}/mpi.json")) == {"version": 2}
    for version, files in seen:
        if version == 2:
            assert files == [bytes([2])] * len(names), "the new manifest was visible before its files"
    if isinstance(storage, S3Storage):
        assert written[-1] == "mpi.json" and sorted(written[:-1]) == names


# -- S3 alone -----------------------------------------------------------------------------------

WRITER = """
import sys, threading, time
from pathlib import Path
from service.storage.s3 import S3Storage

endpoint, bucket, src, work = sys.argv[1:]
storage = S3Storage(bucket, "cmc", work, endpoint, multipart_bytes=5 << 20)

printing = threading.Lock()

def part_done(**kw):
    with printing:  # parts upload on several threads: one whole line each
        print("part", flush=True)
    time.sleep(0.5)  # slow enough for the test to kill this process mid-upload

storage.client.meta.events.register("after-call.s3.UploadPart", part_done)
storage.publish("%s/checkpoint.pt", Path(src))
print("done", flush=True)
"""


def test_worker_killed_mid_upload_leaves_the_previous_checkpoint(s3: str, tmp_path: Path) -> None:
    bucket = new_bucket(s3)
    storage = S3Storage(bucket, "cmc", tmp_path / "work", s3, multipart_bytes=5 << 20)
    key = f"{SCENE}/checkpoint.pt"
    previous = tmp_path / "step100.pt"
    torch.save({"step": 100, "model": {"w": torch.arange(10.0)}}, previous)
    storage.publish(key, previous)
    # the next checkpoint: 40 MB, 8 parts of 5 MB
    big = tmp_path / "step200.pt"
    torch.save({"step": 200, "model": {"w": torch.zeros(10 << 20)}}, big)
    writer = subprocess.Popen(
        [sys.executable, "-c", WRITER % SCENE, s3, bucket, str(big), str(tmp_path / "work2")],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert writer.stdout is not None
        assert writer.stdout.readline().strip() == "part", "the upload did not start in parts"
        os.kill(writer.pid, signal.SIGKILL)
    finally:
        writer.kill()
        writer.wait(10)
    assert writer.returncode == -signal.SIGKILL
    uploads = storage.client.list_multipart_uploads(Bucket=bucket).get("Uploads", [])
    assert [u["Key"] for u in uploads] == [f"cmc/{key}"], "the writer was not killed mid-upload"
    ckpt = torch.load(io.BytesIO(storage.read_bytes(key)), weights_only=True)
    assert ckpt["step"] == 100 and torch.equal(ckpt["model"]["w"], torch.arange(10.0))
    storage.publish(key, big)  # the next writer gets through
    assert torch.load(io.BytesIO(storage.read_bytes(key)), weights_only=True)["step"] == 200


def test_presigned_url_downloads_the_stored_bytes(s3: str, tmp_path: Path) -> None:
    storage = S3Storage(new_bucket(s3), "cmc", tmp_path / "work", s3, url_seconds=600)
    data = os.urandom(100_000)
    storage.write_bytes(f"{SCENE}/videos/orbit.mp4", data)
    url = storage.locate(f"{SCENE}/videos/orbit.mp4", "video/mp4", "orbit.mp4")
    assert url.startswith(s3) and "X-Amz-Signature=" in url and "X-Amz-Expires=600" in url
    with urllib.request.urlopen(url, timeout=10) as r:
        assert r.read() == data
        assert r.headers["Content-Type"] == "video/mp4"
        assert r.headers["Content-Disposition"] == 'attachment; filename="orbit.mp4"'
    # signed for the address clients use when the service reaches the bucket at another one
    public = S3Storage(storage.bucket, "cmc", tmp_path / "work", s3, public_endpoint_url="https://files.example.com")
    assert public.locate(f"{SCENE}/videos/orbit.mp4", "video/mp4").startswith("https://files.example.com/")


def test_bad_storage_settings_are_readable_errors(s3: str, tmp_path: Path) -> None:
    for bad in ("/data/storage", "s3://", "s3://UPPER/x", "gs://bucket"):
        with pytest.raises(ValidationError, match="CMC_STORAGE must be empty or s3://bucket"):
            load_settings(data_dir=tmp_path, storage=bad)
    missing = load_settings(data_dir=tmp_path, storage="s3://no-such-bucket/cmc", s3_endpoint_url=s3)
    with pytest.raises(StorageError, match="cannot write to S3Storage.s3://no-such-bucket/cmc at http"):
        open_storage(missing)
    closed = f"http://127.0.0.1:{free_port()}"
    down = load_settings(data_dir=tmp_path, storage="s3://cmc/x", s3_endpoint_url=closed)
    with pytest.raises(StorageError, match="Could not connect to the endpoint URL"):
        create_app(down)


# -- a job end to end, embedded, with S3 storage -------------------------------------------------


@pytest.fixture(scope="module")
def s3_ready(s3: str, tmp_path_factory) -> Iterator[tuple[TestClient, str, Path]]:
    """(client, scene id, data dir) of a scene trained to ``ready`` by the embedded service
    storing its artifacts in a bucket; the files in its local working folders at the moment the
    job made the scene ready in ``client.work_at_ready``."""
    tmp = tmp_path_factory.mktemp("s3-ready")
    bucket = new_bucket(s3)
    settings = load_settings(
        data_dir=tmp,
        mode="embedded",
        api_keys="",
        api_keys_file=None,
        allowed_hosts="testserver",
        heartbeat_seconds=0.2,
        storage=f"s3://{bucket}/jobs",
        s3_endpoint_url=s3,
    )
    parts, _, novel = synthetic_upload(steps=25)
    app = create_app(settings)
    store, work_dir, work_at_ready = app.state.services.store, app.state.services.storage.work_dir, []
    advance = store.advance

    def recording_advance(scene_id, worker, phase, status, **fields):
        if status == "ready":
            work_at_ready.extend(p for p in work_dir.rglob("*") if p.is_file())
        return advance(scene_id, worker, phase, status, **fields)

    store.advance = recording_advance
    with TestClient(app) as client:
        client.novel = novel  # type: ignore[attr-defined]
        client.work_at_ready = work_at_ready  # type: ignore[attr-defined]
        r = client.post("/v1/scenes", files=parts)
        assert r.status_code == 202, r.text
        sid = r.json()["id"]
        t0 = time.time()
        while (body := client.get(f"/v1/scenes/{sid}").json())["status"] not in ("ready", "failed"):
            assert time.time() - t0 < 240, body
            time.sleep(0.2)
        assert body["status"] == "ready", body
        yield client, sid, tmp


def download(client: TestClient, url: str) -> tuple[bytes, str]:
    """GET an API download: a 307 to a presigned bucket URL, fetched with urllib (not the API)."""
    r = client.get(url, follow_redirects=False)
    assert r.status_code == 307, r.text
    with urllib.request.urlopen(r.headers["location"], timeout=30) as f:
        return f.read(), f.headers["Content-Type"]


def test_job_end_to_end_stores_everything_in_the_bucket(s3_ready) -> None:
    client, sid, data_dir = s3_ready
    storage = client.app.state.services.storage
    assert isinstance(storage, S3Storage)
    keys = storage.list(sid)
    assert {f"{sid}/uploads/{n}" for n in ("00.png", "01.png", "02.png", "cameras.json")} <= set(keys)
    assert f"{sid}/scene/cameras.json" in keys and f"{sid}/baked/mpi.json" in keys
    # removed once baked: the job turns ``ready`` first (so a worker that lost its lease never
    # deletes the checkpoint of the one now holding it), then deletes it
    t0 = time.time()
    while f"{sid}/checkpoint.pt" in storage.list(sid):
        assert time.time() - t0 < 10, "the checkpoint was not removed after the bake"
        time.sleep(0.1)
    assert not (data_dir / "storage").exists(), "artifacts were written to the local folder"
    assert list((data_dir / "work").iterdir()) == [], "working copies were left behind"
    assert client.work_at_ready == [], "the job said ready before its working copies were removed"
    assert client.get(f"/v1/scenes/{sid}/cameras").status_code == 200


def test_render_cache_loads_the_baked_scene_from_the_bucket(s3_ready) -> None:
    client, sid, _ = s3_ready
    cache = client.app.state.services.renders
    cache.evict(sid)
    r = client.post(f"/v1/scenes/{sid}/render", json=render_body(client.novel))
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert f"{sid}/baked" in cache._scenes and cache.nbytes > 0
    assert np.asarray(Image.open(io.BytesIO(r.content))).std() > 0.01


def test_downloads_redirect_to_presigned_urls(s3_ready) -> None:
    client, sid, _ = s3_ready
    storage = client.app.state.services.storage
    manifest = client.get(f"/v1/scenes/{sid}/mpi")  # small: answered by the API itself
    assert manifest.status_code == 200 and manifest.json()["format"] == "cmc-mpi"
    atlas = manifest.json()["mpis"][0]["atlas"]
    data, ctype = download(client, f"/v1/scenes/{sid}/mpi/{atlas}")
    assert data == storage.read_bytes(f"{sid}/baked/{atlas}") and ctype == "image/png"
    glb, ctype = download(client, f"/v1/scenes/{sid}/export.glb")
    assert glb[:4] == b"glTF" and ctype == "model/gltf-binary"
    assert client.get(f"/v1/scenes/{sid}/video?path=orbit").status_code == 202
    t0 = time.time()
    while client.get(f"/v1/scenes/{sid}/video?path=orbit", follow_redirects=False).status_code == 202:
        assert time.time() - t0 < 180
        time.sleep(0.5)
    video, ctype = download(client, f"/v1/scenes/{sid}/video?path=orbit")
    assert video[4:8] == b"ftyp" and ctype == "video/mp4"
    assert not storage.exists(f"{sid}/videos/orbit.json")


def test_delete_removes_the_scene_from_the_bucket(s3_ready) -> None:
    client, sid, _ = s3_ready
    storage = client.app.state.services.storage
    assert client.delete(f"/v1/scenes/{sid}").status_code == 204
    assert storage.list(sid) == []
