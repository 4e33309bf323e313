"""Bounded memory at intake (issue 15, item 1): concurrent worst-case uploads stay under a stated
ceiling in the API process, and uploads waiting for decode memory hold up nothing else.

The worst case is a photo that is small on the wire and large in memory: one flat colour, with
alpha, at exactly the pixel limit (a 4000 x 3000 PNG here is 60 KB and 96 MB decoded to RGBA).
The server runs as a child process, so its resident high-water mark is its own.
"""

from __future__ import annotations

import io
import os
import signal
import socket
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx2
import pytest
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
MIB = 1 << 20


class NoJobs:
    """A job queue that runs nothing: what is measured is intake alone."""

    def submit(self, scene_id: str, phase: str) -> None:
        pass

    def submit_video(self, scene_id: str, path: str) -> None:
        pass

    def depth(self) -> dict[str, int]:
        return {}

    def ping(self) -> None:
        pass


SERVER = """
import sys, uvicorn
sys.path.insert(0, sys.argv[2])
from test_intake_memory import NoJobs
from service.app import create_app
uvicorn.run(create_app(queue=NoJobs()), host="127.0.0.1", port=int(sys.argv[1]), log_level="warning")
"""


def _memory(pid: int) -> dict[str, int]:
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = int(value.split()[0]) * 1024
    return fields


def _flat_png(width: int, height: int) -> bytes:
    buf = io.BytesIO()
    Image.new("RGBA", (width, height), (40, 90, 160, 200)).save(buf, "PNG")
    return buf.getvalue()


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc (Linux)")
def test_concurrent_worst_case_uploads_stay_under_the_memory_ceiling(tmp_path: Path) -> None:
    """8 uploads of three 12 MP flat PNGs at once (96 MB each decoded): the API's peak stays within
    its idle memory + one decode + 64 MiB. Before the budget every photo was decoded in parallel,
    and three times over (the EXIF read, the decode, an upright copy and an RGB copy)."""
    budget, width, height = 64 * MIB, 4000, 3000
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "OMP_NUM_THREADS": "1",
        "CMC_DATA_DIR": str(tmp_path / "data"),
        "CMC_API_KEYS": "",
        "CMC_MAX_IMAGE_PIXELS": str(width * height),
        "CMC_DECODE_MEMORY_BYTES": str(budget),
    }
    env.pop("CMC_API_KEYS_FILE", None)
    log = tmp_path / "server.log"
    with open(log, "wb") as out:
        args = [sys.executable, "-c", SERVER, str(port), str(Path(__file__).parent)]
        server = subprocess.Popen(args, env=env, stdout=out, stderr=out, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        t0 = time.time()
        while True:
            assert server.poll() is None and time.time() - t0 < 60, log.read_text()
            try:
                if httpx2.get(f"{url}/healthz", timeout=2).status_code == 200:
                    break
            except httpx2.HTTPError:
                time.sleep(0.1)
        small = [("images", (f"s{k}.png", _flat_png(96, 72), "image/png")) for k in range(3)]
        assert httpx2.post(f"{url}/v1/scenes", files=small, timeout=60).status_code == 202  # imports everything
        idle = _memory(server.pid)["VmRSS"]
        photo = _flat_png(width, height)
        files = [("images", (f"flat{k}.png", photo, "image/png")) for k in range(3)]
        with ThreadPoolExecutor(8) as pool:
            answers = list(pool.map(lambda _: httpx2.post(f"{url}/v1/scenes", files=files, timeout=300), range(8)))
        peak = _memory(server.pid)["VmHWM"]
    finally:
        os.killpg(server.pid, signal.SIGKILL)
        server.wait(10)
    assert [r.status_code for r in answers] == [202] * 8, [r.text[:200] for r in answers]
    one_decode = width * height * 8 + 8 * MIB  # cmc.data.images.decode_bytes of an RGBA PNG
    ceiling = idle + max(budget, one_decode) + 64 * MIB
    assert peak <= ceiling, f"peak {peak / MIB:.0f} MiB > {ceiling / MIB:.0f} MiB (idle {idle / MIB:.0f} MiB)"


def test_uploads_waiting_for_decode_memory_never_hold_up_probes_and_status(tmp_path: Path) -> None:
    """Uploads whose decodes wait for memory wait on threads of their own, not on the thread
    pool of the other routes: 48 of them (more than that pool's 40 threads) leave probes and
    status polls answering at once, and all complete once memory is free."""
    import threading

    import uvicorn

    from service.app import create_app
    from service.settings import load_settings

    settings = load_settings(data_dir=tmp_path, mode="embedded", api_keys="", api_keys_file=None)
    app = create_app(settings, queue=NoJobs())
    budget = app.state.services.decode_memory  # what the upload checks' decodes draw on
    server = uvicorn.Server(uvicorn.Config(app, port=0, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        assert thread.is_alive(), "uvicorn did not start"
        time.sleep(0.02)
    port = server.servers[0].sockets[0].getsockname()[1]
    files = [("images", (f"s{k}.png", _flat_png(96, 72), "image/png")) for k in range(3)]
    try:
        with httpx2.Client(base_url=f"http://127.0.0.1:{port}", timeout=120) as client, ThreadPoolExecutor(48) as pool:
            sid = client.post("/v1/scenes", files=files).json()["id"]
            with budget.reserve(budget.capacity):  # every decode now waits
                uploads = [pool.submit(client.post, "/v1/scenes", files=files) for _ in range(48)]
                time.sleep(1.0)  # all of them arrived and wait
                assert not any(u.done() for u in uploads)
                for path in ("/healthz", "/readyz", f"/v1/scenes/{sid}"):
                    t0 = time.perf_counter()
                    assert client.get(path, timeout=5).status_code == 200
                    assert time.perf_counter() - t0 < 0.5, path
            assert [u.result().status_code for u in uploads] == [202] * 48
    finally:
        server.should_exit = True
        thread.join(10)
