"""Camera-path videos: an H.264 MP4 that decodes to the rendered frames, and ``cmc render --path``."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cmc.cli import main
from cmc.config import preset_config
from cmc.data.datasets import synthetic_scene
from cmc.eval.metrics import psnr
from cmc.method.training import Trainer
from cmc.serving.baking import BakedScene, bake
from cmc.serving.video import path_cameras, render_path_video

W, H = 64, 48
LUMA = np.array([[0.299], [0.587], [0.114]])  # RGB -> Y (BT.601)


@pytest.fixture(scope="module")
def baked_dir(tmp_path_factory):
    scene = synthetic_scene(num_views=3, width=W, height=H)
    cfg = preset_config("fast", steps=8, rays_per_view=256, unseen_rays=256)
    cfg = replace(cfg, model=replace(cfg.model, num_planes=10))
    trainer = Trainer(scene, cfg)
    trainer.fit()
    return bake(trainer.model, tmp_path_factory.mktemp("video") / "baked")


def decode(path):
    """(metadata, frames [F, H, W, 3] uint8) with the ffmpeg binary of the imageio-ffmpeg wheel."""
    import imageio_ffmpeg

    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    frames = [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in gen]
    return meta, np.stack(frames)


def top_level_boxes(path):
    """Names of the MP4's top-level boxes, in file order."""
    data, pos, names = path.read_bytes(), 0, []
    while pos + 8 <= len(data):
        size = int.from_bytes(data[pos : pos + 4], "big")
        names.append(data[pos + 4 : pos + 8].decode("latin-1"))
        if size == 1:
            size = int.from_bytes(data[pos + 8 : pos + 16], "big")
        if size < 8:
            break
        pos += size
    return names


@pytest.mark.parametrize("kind", ["spiral", "orbit", "dolly"])
def test_path_video_decodes_to_the_rendered_frames(baked_dir, tmp_path, kind):
    baked = BakedScene.load(baked_dir)
    out = render_path_video(baked, kind, tmp_path / f"{kind}.mp4", num_frames=12, fps=10)
    assert out == tmp_path / f"{kind}.mp4"
    assert [p.name for p in tmp_path.iterdir()] == [f"{kind}.mp4"]  # no temporary file left behind
    meta, frames = decode(out)
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p") and meta["fps"] == 10
    assert frames.shape == (12, H, W, 3)
    boxes = top_level_boxes(out)
    assert boxes.index("moov") < boxes.index("mdat")  # faststart: playable while streaming
    # Frames differ along the path (every step moves, except where the dolly turns: frames 2-4
    # and 8-10 render ~2/255 apart and H.264 may repeat a frame there; some reach far from the
    # start) ...
    f = frames.astype(np.float32)
    steps = np.abs(np.diff(f, axis=0)).mean(axis=(1, 2, 3))
    turning = {"dolly": {2, 3, 8, 9}}.get(kind, set())
    assert all(s > 0.1 for k, s in enumerate(steps) if k not in turning), steps
    assert np.abs(f - f[0]).mean(axis=(1, 2, 3)).max() > 5
    # ... and each is the baked render at its pose, up to H.264 (compared in luma: 4:2:0 chroma
    # subsampling blurs this tiny, saturated synthetic texture), closer than to any other pose.
    # Frames 0 and 1 are well apart from their neighbours on every path (the dolly's turning
    # point, frames 2-4, barely moves, and H.264 interpolates such frames); the dolly passes each
    # pose twice, so the best match must be the frame's pose, not necessarily its index.
    K, poses, w, h = path_cameras(baked, kind, 12)
    refs = [baked.render(K, pose, w, h).rgb for pose in poses]
    for i in (0, 1):
        scores = [psnr(frames[i] / 255.0 @ LUMA, ref @ LUMA) for ref in refs]
        best = int(np.argmax(scores))
        assert scores[i] >= 33 and np.allclose(poses[best], poses[i], atol=1e-9), scores


def test_odd_sizes_are_cropped_to_even(baked_dir, tmp_path):
    baked = BakedScene.load(baked_dir)
    meta, frames = decode(render_path_video(baked, "orbit", tmp_path / "o.mp4", num_frames=3, width=33, height=25))
    assert meta["size"] == (32, 24) and frames.shape == (3, 24, 32, 3)


def test_render_command_writes_a_video(baked_dir, tmp_path, capsys):
    out = tmp_path / "v" / "spiral.mp4"
    argv = ["render", str(baked_dir), "--path", "spiral", "--out", str(out), "--frames", "6", "--fps", "6"]
    assert main(argv) == 0
    meta, frames = decode(out)
    assert frames.shape == (6, H, W, 3) and meta["codec"] == "h264"
    assert "wrote" in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, needle",
    [
        ([], "exactly one of --cameras"),
        (["--cameras", "c.json", "--path", "orbit"], "exactly one of --cameras"),
        (["--cameras", "c.json", "--frames", "3"], "--path videos only"),
        (["--path", "orbit", "--frames", "0"], "at least 1"),
    ],
)
def test_render_command_errors(baked_dir, tmp_path, capsys, extra, needle):
    assert main(["render", str(baked_dir), "--out", str(tmp_path / "o.mp4"), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cmc render: error: ") and needle in err and "Traceback" not in err
