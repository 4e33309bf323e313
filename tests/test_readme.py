"""The README's examples as they stand: the curl walk-through run against a real ``cmc serve``,
the ARKit cameras file through the server's parser, the limits against the settings."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx2
import numpy as np
import pytest
from helpers import SHARED_DIR, free_port
from PIL import Image

from cmc.geometry.cameras import camera_file_from_dict, match_frames
from service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
FERN = SHARED_DIR / "datasets" / "llff" / "fern" / "images"
PHOTOS = ("IMG_4027.JPG", "IMG_4036.JPG", "IMG_4045.JPG")


def fenced_block(heading: str, first_line: str) -> str:
    """The first fenced code block under ``heading`` whose first line is ``first_line``."""
    section = README.split(heading, 1)[1]
    for block in re.findall(r"```[a-z]*\n(.*?)```", section, flags=re.S):
        if block.startswith(first_line):
            return block
    raise AssertionError(f"no code block starting with {first_line!r} under {heading!r}")


def walkthrough(**values: str) -> str:
    """The walk-through script with the variables ``values`` (API, F, OPTIONS, OUT) set instead."""
    script = fenced_block("### Walk-through with curl", "#!/usr/bin/env bash")
    for name, value in values.items():
        script, n = re.subn(rf"^{name}=.*$", f"{name}={shlex.quote(value)}", script, flags=re.M)
        assert n == 1, f"the walk-through no longer sets {name} on a line of its own"
    return script


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """URL of ``cmc serve`` (the README's command) in a subprocess, with its own data folder."""
    if shutil.which("jq") is None:
        if os.environ.get("CI", "").lower() not in ("", "0", "false"):
            pytest.fail("jq is needed by the README walk-through (make jq installs it)")
        pytest.skip("jq is not installed")
    tmp = tmp_path_factory.mktemp("serve")
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("CMC_")}  # no keys: open on localhost
    cmc = Path(sys.executable).with_name("cmc")
    log = open(tmp / "serve.log", "wb")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(
        [str(cmc), "serve", "--port", str(port), "--data-dir", str(tmp / "data")],
        env={**env, "CMC_DEVICE": "cpu"},
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        t0 = time.time()
        while not _healthy(url):
            assert proc.poll() is None and time.time() - t0 < 60, (tmp / "serve.log").read_text()
            time.sleep(0.3)
        yield url
    finally:
        proc.terminate()
        proc.wait(30)
        log.close()


def _healthy(url: str) -> bool:
    try:
        return httpx2.get(f"{url}/healthz", timeout=2).status_code == 200
    except httpx2.HTTPError:
        return False


def run(script: str, cwd: Path) -> subprocess.CompletedProcess:
    path = cwd / "walk.sh"
    path.write_text(script)
    return subprocess.run(["bash", "-euo", "pipefail", str(path)], cwd=cwd, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    """The README's three fern photos, downscaled to 504 px (EXIF kept: SfM's focal prior)."""
    if not FERN.exists():
        pytest.skip(f"needs the LLFF fern photos in {FERN}")
    folder = tmp_path_factory.mktemp("photos")
    for name in PHOTOS:
        with Image.open(FERN / name) as im:
            exif = im.info.get("exif", b"")
            im.thumbnail((504, 504))
            im.save(folder / name, "JPEG", quality=90, exif=exif)
    return folder


def test_curl_walkthrough_runs_as_written(server: str, photos: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    options = json.dumps({"steps": 4, "resolution": 64})
    r = run(walkthrough(API=server, F=str(photos), OPTIONS=options, OUT=str(out)), tmp_path)
    assert r.returncode == 0, f"stdout:\n{r.stdout}\nstderr:\n{r.stderr}"
    assert '"status":"ready"' in r.stdout and f"results in {out}" in r.stdout
    view = Image.open(out / "view.png")
    assert view.format == "PNG" and view.size == (64, 48)
    depth = np.load(out / "depth.npy")
    assert depth.shape == (48, 64) and (depth > 0).mean() > 0.9
    assert Image.open(out / "depth.png").format == "PNG"
    # the rendered camera is a novel one: none of the photos' cameras
    camera = json.loads((out / "camera.json").read_text())
    centres = [np.array(f["transform_matrix"])[:3, 3] for f in json.loads((out / "cameras.json").read_text())["frames"]]
    assert min(np.linalg.norm(np.array(camera["transform_matrix"])[:3, 3] - c) for c in centres) > 1e-3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "walk.sh"]  # nothing left in the working folder


def test_curl_walkthrough_stops_on_errors(server: str, photos: Path, tmp_path: Path) -> None:
    """An API error stops the script with the API's message; a failed job exits non-zero."""
    refused = run(walkthrough(API=server, F=str(photos), OPTIONS='{"steps": 0}', OUT=str(tmp_path)), tmp_path)
    assert refused.returncode != 0 and "invalid_options" in refused.stderr
    blank = tmp_path / "blank"
    blank.mkdir()
    for k, name in enumerate(PHOTOS):  # featureless photos: pose estimation fails
        Image.new("RGB", (96, 72), (100 + k, 100, 100)).save(blank / name, "PNG")
    failed = run(walkthrough(API=server, F=str(blank), OPTIONS="{}", OUT=str(tmp_path)), tmp_path)
    assert failed.returncode == 1 and "job failed:" in failed.stderr, failed.stderr
    assert any(name in failed.stderr for name in PHOTOS)  # the message names the photos
    assert not (tmp_path / "view.png").exists()


def test_arkit_example_is_accepted_by_the_cameras_parser() -> None:
    heading = "### Poses from ARKit or ARCore"
    cf = camera_file_from_dict(json.loads(fenced_block(heading, "{")))
    assert (cf.cameras.width, cf.cameras.height) == (1920, 1440) and cf.near_far is None
    # the request example's photos are the frames' photos, as the server matches them
    request = fenced_block(heading, "curl")
    names = re.findall(r"images=@(\S+)", request)
    assert match_frames(cf.file_paths, [(n,) for n in names]) == [0, 1, 2]
    # the prose: 15 cm steps sideways, every camera turned towards a point 2 m ahead (ARKit's -z)
    centres = cf.cameras.centers
    np.testing.assert_allclose(np.diff(centres, axis=0), [[0.15, 0, 0]] * 2, atol=1e-9)
    target = centres[1] + [0.0, 0.0, -2.0]
    axes = cf.cameras.world_from_cam[:, :3, 2]  # optical axes (OpenCV z) in the world
    to_target = target - centres
    off_axis = np.linalg.norm(np.cross(axes, to_target), axis=1) / np.linalg.norm(to_target, axis=1)
    assert off_axis.max() < 1e-3


def _table_rows(section: str) -> list[tuple[str, str]]:
    """(setting names, default values) of a README limits table: `| what | settings | defaults | ... |`."""
    return re.findall(r"^\|[^|]*\| (`CMC_\w+`(?: / `CMC_\w+`)?) \| ([^|]+?) \|", section, flags=re.M)


@pytest.mark.parametrize("title, rows", [("### Upload limits", 7), ("### Quotas and rate limits", 3)])
def test_limits_tables_give_the_settings_defaults(title: str, rows: int) -> None:
    defaults = Settings.model_construct()  # the defaults, not this environment's CMC_* values
    section = README.split(title, 1)[1].split("###", 1)[0]
    assert len(_table_rows(section)) == rows
    for names, values in _table_rows(section):
        fields = [n.strip("`").removeprefix("CMC_").lower() for n in names.split(" / ")]
        numbers = [float(v.split()[0]) for v in values.split(" / ")]
        assert numbers == [getattr(defaults, f) for f in fields], names
    if title == "### Upload limits":
        assert f"({defaults.max_request_bytes} by default" in section
