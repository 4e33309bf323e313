"""glTF export of a baked MPI (cmc.serving.gltf, ``cmc export``, ``GET /v1/scenes/{id}/export.glb``),
read back with pygltflib (an independent glTF reader) and checked against the known synthetic
scene: plane geometry where the reference camera's frustum puts it, the atlas tiles as
textures, the input cameras as glTF cameras whose projection puts a 3D point on the pixel where
the scene's camera sees it."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from fastapi.testclient import TestClient
from PIL import Image
from test_service_api import RecordingQueue, settings_for

from cmc.cli import main as cli
from cmc.config import preset_config
from cmc.data.datasets import synthetic_scene
from cmc.geometry.cameras import Cameras
from cmc.method.training import Trainer
from cmc.serving.baking import bake
from cmc.serving.gltf import export_glb
from service.app import create_app

W, H = 48, 36


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> tuple[Path, object]:
    """A baked folder of the three-view synthetic scene (an untrained model: its plane-sweep
    start gives every plane its own content) and the scene."""
    scene = synthetic_scene(num_views=3, width=W, height=H)
    folder = tmp_path_factory.mktemp("gltf") / "baked"
    bake(Trainer(scene, preset_config("fast", steps=1, rays_per_view=64, unseen_rays=64)).model, folder)
    return folder, scene


def read(data: bytes) -> tuple[pygltflib.GLTF2, bytes]:
    g = pygltflib.GLTF2.load_from_bytes(data)
    return g, g.binary_blob()


def accessor(g: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    a = g.accessors[index]
    view = g.bufferViews[a.bufferView]
    dtype = {pygltflib.FLOAT: np.float32, pygltflib.UNSIGNED_SHORT: np.uint16}[a.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[a.type]
    start = view.byteOffset + (a.byteOffset or 0)
    return np.frombuffer(blob, dtype, a.count * width, start).reshape(a.count, width).squeeze()


def image(g: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    view = g.bufferViews[g.images[index].bufferView]
    return np.asarray(Image.open(io.BytesIO(blob[view.byteOffset : view.byteOffset + view.byteLength])))


def node_matrix(node: pygltflib.Node) -> np.ndarray:
    return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF stores column-major


def test_glb_holds_the_nearest_mpi_planes_with_their_textures(baked) -> None:
    folder, scene = baked
    manifest = json.loads((folder / "mpi.json").read_text())
    data, index = export_glb(folder)
    assert data[:4] == b"glTF"
    g, blob = read(data)
    # the middle camera of the triangle is nearest the mean camera (centres -0.15, 0, 0.15 in x)
    assert index == 1 and g.scenes[0].extras["mpi"] == 1
    entry = manifest["mpis"][1]
    (mesh,) = g.meshes
    depths = entry["depths"]
    assert len(mesh.primitives) == len(depths) == preset_config("fast").model.num_planes
    (_, cols), (th, tw) = entry["grid"], entry["tile"]
    atlas = np.asarray(Image.open(folder / entry["atlas"]).convert("RGBA"))
    ref = Cameras(np.array(entry["K"])[None], np.array(entry["world_from_cam"])[None], W, H)
    (mx, my) = entry["margin"]
    x0, x1, y0, y1 = (1 - mx) / 2 * W, (1 + mx) / 2 * W, (1 - my) / 2 * H, (1 + my) / 2 * H  # the extent's corners
    expected_uv = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    seen_depths = []
    for prim in mesh.primitives:
        material = g.materials[prim.material]
        k = material.extras["plane"]
        seen_depths.append(depths[k])
        assert material.alphaMode == "BLEND" and material.doubleSided
        assert "KHR_materials_unlit" in material.extensions
        # geometry: the plane's corners, seen by the reference camera at the extent's corners and depth k
        corners = accessor(g, blob, prim.attributes.POSITION)
        uv, z = ref.project(corners.astype(np.float64))
        np.testing.assert_allclose(uv[0], expected_uv, atol=1e-3)
        np.testing.assert_allclose(z[0], depths[k], rtol=1e-5)
        np.testing.assert_allclose(g.accessors[prim.attributes.POSITION].min, corners.min(0), rtol=1e-6)
        np.testing.assert_allclose(accessor(g, blob, prim.attributes.TEXCOORD_0), [[0, 0], [1, 0], [1, 1], [0, 1]])
        assert sorted(accessor(g, blob, prim.indices).tolist()) == [0, 0, 1, 2, 2, 3]
        # texture: the plane's tile of the atlas, the back plane opaque
        tex = image(g, blob, g.textures[material.pbrMetallicRoughness.baseColorTexture.index].source)
        r, c = divmod(k, cols)
        tile = atlas[r * th : (r + 1) * th, c * tw : (c + 1) * tw].copy()
        if k == len(depths) - 1:
            tile[..., 3] = 255
        np.testing.assert_array_equal(tex, tile)
    assert seen_depths == sorted(depths, reverse=True)  # far to near: blended back to front
    assert len(set(np.asarray(seen_depths).round(6))) == len(depths)  # every plane once
    assert g.samplers[0].wrapS == g.samplers[0].wrapT == 33071  # clamped: nothing wraps round the edges
    assert export_glb(folder, mpi=2)[1] == 2
    with pytest.raises(ValueError, match="mpi must be 0 to 2"):
        export_glb(folder, mpi=3)


def test_glb_cameras_project_points_where_the_scene_cameras_do(baked) -> None:
    """glTF cameras look down -Z with +Y up: a world point goes through the root node and the
    camera node's inverse, then glTF's perspective projection, and must land on the pixel where
    the scene's own camera (OpenCV convention) projects it."""
    folder, scene = baked
    g, _ = read(export_glb(folder, camera_names=["a.png", "b.png", "c.png"])[0])
    root = g.nodes[g.scenes[0].nodes[0]]
    file_from_world = node_matrix(root)
    rng = np.random.default_rng(0)
    cams = scene.cameras
    for i in range(3):
        (node,) = [g.nodes[c] for c in root.children if g.nodes[c].camera == i]
        assert node.name == g.cameras[i].name == ["a.png", "b.png", "c.png"][i]
        persp = g.cameras[i].perspective
        assert persp.aspectRatio == pytest.approx(W / H)
        view = np.linalg.inv(file_from_world @ node_matrix(node))  # camera from file frame
        # points in front of camera i at depths between near and far, all over its image
        pix = np.stack([rng.uniform(0, W, 50), rng.uniform(0, H, 50), np.ones(50)], 1)
        depth = rng.uniform(*scene.near_far[i], 50)
        pts = (depth[:, None] * pix @ np.linalg.inv(cams.K[i]).T) @ cams.world_from_cam[i, :3, :3].T
        pts += cams.world_from_cam[i, :3, 3]
        uv_cmc, z_cmc = cams[i : i + 1].project(pts)
        p = (view @ file_from_world @ np.c_[pts, np.ones(50)].T).T[:, :3]  # world -> file frame -> camera
        assert (p[:, 2] < 0).all()  # in front: down -Z
        f = 1 / math.tan(persp.yfov / 2)
        ndc = np.stack([f / persp.aspectRatio * p[:, 0] / -p[:, 2], f * p[:, 1] / -p[:, 2]], 1)
        uv_gl = np.stack([(ndc[:, 0] + 1) / 2 * W, (1 - ndc[:, 1]) / 2 * H], 1)  # +Y up: rows grow downwards
        np.testing.assert_allclose(uv_gl, uv_cmc[0], atol=1e-4)  # the manifest holds float32 poses
        np.testing.assert_allclose(-p[:, 2], z_cmc[0], rtol=1e-6)
        assert persp.znear < scene.near_far[i][0] and persp.zfar > scene.near_far[i][1]
    # the root puts the mean camera at the origin, looking down -Z with +Y up (the image's up)
    centres = file_from_world[:3, :3] @ cams.centers.T + file_from_world[:3, 3:4]
    np.testing.assert_allclose(centres.mean(1), 0, atol=1e-9)
    forward = file_from_world[:3, :3] @ cams.world_from_cam[1, :3, 2]  # camera 1 looks along +z (OpenCV)
    up = file_from_world[:3, :3] @ -cams.world_from_cam[1, :3, 1]  # and its image's up is -y
    assert forward[2] < -0.99 and up[1] > 0.99


def test_cli_export(baked, tmp_path: Path, capsys) -> None:
    folder, _ = baked
    out = tmp_path / "out" / "scene.glb"
    assert cli(["export", str(folder), "--out", str(out), "--mpi", "0"]) == 0
    g, _ = read(out.read_bytes())
    assert g.scenes[0].extras["mpi"] == 0 and g.meshes[0].name == "mpi_00"
    assert "MPI 0" in capsys.readouterr().out
    assert cli(["export", str(tmp_path), "--out", str(out)]) == 2
    assert "cmc export: error: no mpi.json" in capsys.readouterr().err


def test_export_route(baked, tmp_path: Path) -> None:
    folder, _ = baked
    app = create_app(settings_for(tmp_path), queue=RecordingQueue())
    svc = app.state.services
    rec, _ = svc.store.create("local", {}, ["left.jpg", "mid.jpg", "right.jpg"], ["00.jpg", "01.jpg", "02.jpg"], False)
    with TestClient(app) as client:
        assert client.get(f"/v1/scenes/{rec.id}/export.glb").json()["error"]["code"] == "scene_not_ready"
        assert svc.store.claim(rec.id, "poses", "test", 60) is not None
        assert svc.store.advance(rec.id, "test", "done", "ready")
        for f in folder.iterdir():
            svc.storage.write_bytes(f"{rec.id}/baked/{f.name}", f.read_bytes())
        r = client.get(f"/v1/scenes/{rec.id}/export.glb")
        assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary"
        assert r.content == export_glb(folder, camera_names=["left.jpg", "mid.jpg", "right.jpg"])[0]
        assert [c.name for c in read(r.content)[0].cameras] == ["left.jpg", "mid.jpg", "right.jpg"]
        assert (tmp_path / "storage" / rec.id / "exports" / "mpi_01.glb").exists()  # built once, then served
        other = client.get(f"/v1/scenes/{rec.id}/export.glb?mpi=2")
        assert read(other.content)[0].scenes[0].extras["mpi"] == 2
        bad = client.get(f"/v1/scenes/{rec.id}/export.glb?mpi=3")
        assert bad.status_code == 422 and bad.json()["error"]["code"] == "invalid_mpi"
        assert client.get(f"/v1/scenes/{rec.id}").json()["links"]["export_glb"] == f"/v1/scenes/{rec.id}/export.glb"
