"""glTF 2.0 export of a baked MPI: textured, alpha-blended quads plus the input cameras, as one
binary ``.glb`` that any glTF viewer opens (three.js, Blender, model-viewer).

What the file holds (``export_glb``):

* One mesh: the planes of one MPI (by default the MPI whose reference camera is nearest the
  scene's mean camera, :func:`nearest_mpi`), one primitive per plane, ordered far to near so
  that viewers which draw a mesh's primitives in order (three.js) blend them back to front.
  Each plane is a quad at its depth in the MPI's reference camera, spanning the plane's extent
  (the image enlarged ``margin`` times about its centre, as in :mod:`cmc.serving.baking`), with its
  RGBA tile as texture: straight alpha, ``alphaMode: BLEND``, unlit (``KHR_materials_unlit``),
  linear filtering, clamped at the edges. The back plane is opaque, as in the renderer.
* One perspective camera per input view (the reference camera of each MPI), named
  ``view_<i>`` or by the names given. glTF cameras look down their -Z axis with +Y up: the pose
  is the OpenCV ``world_from_cam`` with its y and z axes negated (:func:`cmc.geometry.cameras.convert_pose`).
  ``yfov = 2 atan(h / 2 fy)`` and ``aspectRatio = w / h``: exact for square pixels and a
  centred principal point; glTF cannot express other intrinsics, so those views are approximate.
* Node ``cmc-scene`` (the root) maps the scene's world to the file's frame, placing the mean
  input camera at the origin looking down -Z with +Y up, so that viewers, which take +Y as up,
  show the capture upright. Its children (the mesh's node and the camera nodes) are in the
  scene's world coordinates and units; the inverse of the root's matrix gives them back.

The GLB is written here (a JSON chunk and a binary chunk, about a hundred lines) rather than with
a glTF library, so that the library and service need no dependency for it; the tests read the
files back with pygltflib.
"""

from __future__ import annotations

import io
import json
import math
import struct
from pathlib import Path

import numpy as np
from PIL import Image

from cmc.errors import ConfigError
from cmc.geometry.camera_paths import mean_pose
from cmc.geometry.cameras import convert_pose, pixel_rays

GLB_MAGIC, GLB_VERSION, CHUNK_JSON, CHUNK_BIN = 0x46546C67, 2, 0x4E4F534A, 0x004E4942
FLOAT, UNSIGNED_SHORT = 5126, 5123
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
LINEAR, CLAMP_TO_EDGE = 9729, 33071


def nearest_mpi(manifest: dict) -> int:
    """Index of the MPI whose reference camera centre is nearest the mean input camera's."""
    poses = np.array([m["world_from_cam"] for m in manifest["mpis"]], dtype=np.float64)
    centre = mean_pose(poses)[:3, 3]
    return int(np.argmin(np.linalg.norm(poses[:, :3, 3] - centre, axis=1)))


def scene_root(manifest: dict) -> np.ndarray:
    """[4, 4] the root node's matrix: file frame from scene world (the mean camera, OpenGL axes,
    moved to the origin)."""
    poses = np.array([m["world_from_cam"] for m in manifest["mpis"]], dtype=np.float64)
    return np.linalg.inv(convert_pose(mean_pose(poses), "opencv", "opengl"))


def plane_corners(
    K: np.ndarray, world_from_cam: np.ndarray, depth: float, width: int, height: int, margin: tuple[float, float]
):
    """[4, 3] world corners of a plane (top-left, top-right, bottom-right, bottom-left as the
    reference camera sees it): the image's extent enlarged ``margin`` (x, y) times, at camera z ``depth``."""
    u0, u1 = (1 - margin[0]) / 2 * width, (1 + margin[0]) / 2 * width
    v0, v1 = (1 - margin[1]) / 2 * height, (1 + margin[1]) / 2 * height
    corners = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], dtype=np.float64)
    cam = depth * pixel_rays(K, corners)
    return cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]


def gltf_camera(K: np.ndarray, width: int, height: int, near: float, far: float) -> dict:
    """A glTF perspective camera for intrinsics K (square pixels, centred principal point)."""
    return {
        "type": "perspective",
        "perspective": {
            "yfov": 2 * math.atan(height / (2 * float(K[1, 1]))),
            "aspectRatio": width / height,
            "znear": 0.05 * near,
            "zfar": 20 * far,
        },
    }


class _Bin:
    """The binary chunk: 4-byte aligned buffer views, appended in order."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []

    def add(self, blob: bytes, target: int | None = None) -> int:
        self.data += b"\0" * (-len(self.data) % 4)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(blob)}
        if target is not None:
            view["target"] = target
        self.data += blob
        self.views.append(view)
        return len(self.views) - 1


def _png(rgba: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(buf, "PNG", compress_level=6)
    return buf.getvalue()


def _column_major(m: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(m, dtype=np.float64).T.reshape(-1)]


def export_glb(baked: str | Path, mpi: int | None = None, camera_names: list[str] | None = None) -> tuple[bytes, int]:
    """The GLB of baked folder ``baked`` (mpi.json + atlases): MPI ``mpi`` (default
    :func:`nearest_mpi`) and every input camera. Returns (file bytes, the MPI's index)."""
    from cmc.serving.baking import MANIFEST, BakedFormatError

    folder = Path(baked)
    try:
        manifest = json.loads((folder / MANIFEST).read_text())
    except FileNotFoundError:
        raise BakedFormatError(f"no {MANIFEST} in {folder}: not a baked MPI folder") from None
    entries = manifest["mpis"]
    index = nearest_mpi(manifest) if mpi is None else mpi
    if not 0 <= index < len(entries):
        raise ConfigError(f"mpi must be 0 to {len(entries) - 1}, got {index}")
    names = camera_names or [f"view_{i}" for i in range(len(entries))]
    if len(names) != len(entries):
        raise ConfigError(f"{len(names)} camera names for {len(entries)} cameras")
    W, H, near, far = int(manifest["width"]), int(manifest["height"]), float(manifest["near"]), float(manifest["far"])
    e = entries[index]
    atlas = _read_atlas(folder, e)
    out = _Bin()
    accessors, images, textures, materials, primitives = _plane_meshes(out, atlas, e, W, H)
    cameras, camera_nodes = _cameras(entries, names, W, H, near, far)
    nodes = [
        {"name": "cmc-scene", "matrix": _column_major(scene_root(manifest)), "children": [*range(1, len(entries) + 2)]},
        {"name": f"mpi_{index:02d}", "mesh": 0},
        *camera_nodes,
    ]
    doc = {
        "asset": {"version": "2.0", "generator": "cmc (cmc.serving.gltf)"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [
            {
                "name": "cmc",
                "nodes": [0],
                "extras": {"mpi": index, "near": near, "far": far, "width": W, "height": H},
            }
        ],
        "nodes": nodes,
        "meshes": [{"name": f"mpi_{index:02d}", "primitives": primitives}],
        "cameras": cameras,
        "materials": materials,
        "textures": textures,
        "samplers": [{"magFilter": LINEAR, "minFilter": LINEAR, "wrapS": CLAMP_TO_EDGE, "wrapT": CLAMP_TO_EDGE}],
        "images": images,
        "accessors": accessors,
        "bufferViews": out.views,
        "buffers": [{"byteLength": len(out.data) + (-len(out.data) % 4)}],
    }
    return _glb(doc, bytes(out.data)), index


def _read_atlas(folder: Path, entry: dict) -> np.ndarray:
    """[rows * h, cols * w, 4] uint8 RGBA atlas of one MPI entry of a manifest, size checked."""
    from cmc.serving.baking import BakedFormatError

    (h, w), (rows, cols) = entry["tile"], entry["grid"]
    with Image.open(folder / Path(entry["atlas"]).name) as im:
        atlas = np.asarray(im.convert("RGBA"))
    if atlas.shape[:2] != (rows * h, cols * w):
        raise BakedFormatError(f"{entry['atlas']} is {atlas.shape[1]}x{atlas.shape[0]}, expected {cols * w}x{rows * h}")
    return atlas


def _plane_meshes(out: _Bin, atlas: np.ndarray, e: dict, W: int, H: int) -> tuple[list, list, list, list, list]:
    """glTF accessors, images, textures, materials and primitives of the planes of MPI entry
    ``e``, far to near (back to front), their data appended to ``out``."""
    from cmc.serving.baking import entry_margin

    K, pose = np.array(e["K"], dtype=np.float64), np.array(e["world_from_cam"], dtype=np.float64)
    (h, w), (_, cols), depths = e["tile"], e["grid"], e["depths"]
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32)  # glTF UV: origin top-left
    faces = np.array([0, 3, 2, 0, 2, 1], dtype=np.uint16)  # counter-clockwise seen from the camera
    accessors = [
        {"bufferView": out.add(uv.tobytes(), ARRAY_BUFFER), "componentType": FLOAT, "count": 4, "type": "VEC2"},
        {"bufferView": out.add(faces.tobytes(), ELEMENT_ARRAY_BUFFER), "componentType": UNSIGNED_SHORT,
         "count": 6, "type": "SCALAR"},
    ]  # fmt: skip
    images, textures, materials, primitives = [], [], [], []
    for k in reversed(range(len(depths))):  # far to near: back to front
        r, c = divmod(k, cols)
        tile = atlas[r * h : (r + 1) * h, c * w : (c + 1) * w].copy()
        if k == len(depths) - 1:
            tile[..., 3] = 255  # the back plane is opaque (cmc.mpi.fields)
        corners = plane_corners(K, pose, float(depths[k]), W, H, entry_margin(e)).astype(np.float32)
        accessors.append(
            {
                "bufferView": out.add(corners.tobytes(), ARRAY_BUFFER),
                "componentType": FLOAT,
                "count": 4,
                "type": "VEC3",
                "min": corners.min(0).tolist(),
                "max": corners.max(0).tolist(),
            }
        )
        images.append({"bufferView": out.add(_png(tile)), "mimeType": "image/png", "name": f"plane_{k:02d}"})
        textures.append({"source": len(images) - 1, "sampler": 0})
        materials.append(
            {
                "name": f"plane_{k:02d}",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {"index": len(textures) - 1},
                    "metallicFactor": 0.0,
                    "roughnessFactor": 1.0,
                },
                "alphaMode": "BLEND",
                "doubleSided": True,
                "extensions": {"KHR_materials_unlit": {}},
                "extras": {"depth": float(depths[k]), "plane": k},
            }
        )
        primitives.append(
            {"attributes": {"POSITION": len(accessors) - 1, "TEXCOORD_0": 0}, "indices": 1,
             "material": len(materials) - 1, "mode": 4}
        )  # fmt: skip

    return accessors, images, textures, materials, primitives


def _cameras(entries: list[dict], names: list[str], W: int, H: int, near: float, far: float) -> tuple[list, list]:
    """glTF cameras and their nodes (OpenGL axes) of every input camera."""
    cameras, camera_nodes = [], []
    for i, entry in enumerate(entries):
        cameras.append({**gltf_camera(np.array(entry["K"]), W, H, near, far), "name": names[i]})
        gl_pose = convert_pose(np.array(entry["world_from_cam"], dtype=np.float64), "opencv", "opengl")
        camera_nodes.append({"name": names[i], "camera": i, "matrix": _column_major(gl_pose)})
    return cameras, camera_nodes


def _glb(doc: dict, binary: bytes) -> bytes:
    """The GLB container: 12-byte header, JSON chunk (space-padded), BIN chunk (zero-padded)."""
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join(
        [
            struct.pack("<III", GLB_MAGIC, GLB_VERSION, total),
            struct.pack("<II", len(text), CHUNK_JSON),
            text,
            struct.pack("<II", len(binary), CHUNK_BIN),
            binary,
        ]
    )
