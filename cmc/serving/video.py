"""Camera-path videos of a baked scene: H.264 MP4 files that browsers play and stream.

Frames are rendered with :meth:`cmc.serving.baking.BakedScene.render` along a path of
:mod:`cmc.geometry.camera_paths` (intrinsics of the first MPI, scaled to the output size) and encoded by
the ffmpeg binary that the ``imageio-ffmpeg`` wheel ships (libx264, yuv420p, ``+faststart`` so
the index sits before the media data). The file appears atomically: it is written under a
temporary name in the same folder and renamed into place, so a reader never sees a partial video.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from cmc.data.images import to_uint8
from cmc.errors import ConfigError
from cmc.geometry.camera_paths import PATH_KINDS, PathKind, camera_path
from cmc.serving.baking import BakedScene

DEFAULT_FRAMES = 120
DEFAULT_FPS = 30


def path_cameras(
    baked: BakedScene, kind: PathKind, num_frames: int, width: int | None = None, height: int | None = None
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The cameras of a path video: K [3, 3] (first MPI's intrinsics scaled from the input size
    to width x height), poses [F, 4, 4] (OpenCV camera-to-world) and the even frame size.

    Odd sizes are cropped by one pixel at the right / bottom (H.264 in yuv420p needs even
    sizes); with corner-origin pixels that leaves K unchanged.
    """
    w, h = int(width or baked.width), int(height or baked.height)
    if w < 2 or h < 2:
        raise ConfigError(f"video size must be at least 2x2, got {w}x{h}")
    K = np.diag([w / baked.width, h / baked.height, 1.0]) @ baked.frames[0].K.cpu().numpy().astype(np.float64)
    refs = np.stack([f.world_from_ref.cpu().numpy().astype(np.float64) for f in baked.frames])
    poses = camera_path(kind, refs, baked.near, baked.far, num_frames)
    return K, poses, w - w % 2, h - h % 2


def render_path_video(
    baked: BakedScene,
    kind: PathKind,
    out_path: str | Path,
    num_frames: int = DEFAULT_FRAMES,
    fps: float = DEFAULT_FPS,
    width: int | None = None,
    height: int | None = None,
    crf: int = 18,
    on_frame: Callable[[int, int], None] | None = None,
) -> Path:
    """Render ``kind`` (``spiral``, ``orbit`` or ``dolly``) through ``baked`` to an MP4 file.

    Args:
        out_path: the .mp4 to write (replaced atomically; its folder must exist).
        num_frames: frames along the closed path; fps: frames per second.
        width, height: output size in pixels (default the input size; odd sizes lose a pixel).
        crf: x264 constant rate factor (lower is better; 18 is visually lossless).
        on_frame: called as ``on_frame(done, total)`` after each encoded frame.
    Returns:
        ``out_path`` as a Path.
    """
    import imageio_ffmpeg

    if kind not in PATH_KINDS:
        raise ConfigError(f"unknown camera path {kind!r}; use one of {', '.join(PATH_KINDS)}")
    if not fps > 0:
        raise ConfigError(f"fps must be positive, got {fps}")
    out = Path(out_path)
    K, poses, w, h = path_cameras(baked, kind, num_frames, width, height)
    # A unique temporary name beside the target (same file system, so the rename is atomic): two
    # builders of the same video, threads or processes, never write into each other's file.
    fd, name = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=".tmp.mp4", dir=out.parent)
    os.close(fd)
    tmp = Path(name)
    tmp.chmod(0o644)  # mkstemp's 0600 would carry over to the video
    writer = imageio_ffmpeg.write_frames(
        str(tmp),
        (w, h),
        fps=fps,
        codec="libx264",
        pix_fmt_in="rgb24",
        pix_fmt_out="yuv420p",
        quality=None,  # rate control by -crf below instead of imageio's bitrate scale
        macro_block_size=2,  # only even sizes, which path_cameras guarantees
        ffmpeg_log_level="error",
        output_params=["-crf", str(int(crf)), "-preset", "medium", "-movflags", "+faststart", "-f", "mp4"],
    )
    try:
        writer.send(None)  # start ffmpeg
        for i, pose in enumerate(poses):
            rgb = baked.render(K, pose, w, h).rgb
            writer.send(np.ascontiguousarray(to_uint8(rgb)))
            if on_frame is not None:
                on_frame(i + 1, len(poses))
        writer.close()
        tmp.replace(out)
    except BaseException:
        writer.close()
        tmp.unlink(missing_ok=True)
        raise
    return out
