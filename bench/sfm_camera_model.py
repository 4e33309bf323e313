"""Relative rotations of SfM on an LLFF scene's three RegNeRF training photos (504x378) against
the dataset's, under two camera models and with the focal length free or fixed at the dataset's
(a one-off diagnostic for bench/poses_e2e.md, 2026-11-27; pycolmap directly, the mapping options
of cmc.poses.sfm).

    PYTHONPATH=. .venv/bin/python bench/sfm_camera_model.py trex SIMPLE_RADIAL fix
"""

import shutil
import sys
from pathlib import Path

import numpy as np
import pycolmap

from cmc.data.datasets import load_llff
from cmc.poses.intake import sift_peak_threshold

scene = sys.argv[1]
model = sys.argv[2]
fix_f = sys.argv[3] == "fix"
split = load_llff(f"../shared/datasets/llff/{scene}")
ids = split.train_ids
gt = split.train.cameras.world_from_cam
f_gt = split.train.cameras.K[0][0, 0]
imgs = sorted(Path(f"../shared/datasets/llff/{scene}/images_8").glob("*.png"))
work = Path(f"/tmp/distort/{scene}_{model}_{sys.argv[3]}")
shutil.rmtree(work, ignore_errors=True)
(work / "img").mkdir(parents=True)
names = []
for i in ids:
    shutil.copy(imgs[i], work / "img" / imgs[i].name)
    names.append(imgs[i].name)
db = work / "db.db"
pycolmap.set_random_seed(0)
reader = pycolmap.ImageReaderOptions()
reader.camera_model = model
if fix_f:
    reader.camera_params = ",".join(str(x) for x in ([f_gt, 252, 189] + ([0.0] if model == "SIMPLE_RADIAL" else [])))
ext = pycolmap.FeatureExtractionOptions()
ext.sift.peak_threshold = sift_peak_threshold(504, ext.sift.peak_threshold)
pycolmap.Database.open(db).close()
pycolmap.import_images(db, work / "img", camera_mode=pycolmap.CameraMode.SINGLE, image_names=names, options=reader)
pycolmap.extract_features(db, work / "img", image_names=names, extraction_options=ext)
pycolmap.match_exhaustive(db)
o = pycolmap.IncrementalPipelineOptions()
o.min_model_size = 2
o.extract_colors = False
o.num_threads = o.mapper.num_threads = 1
o.random_seed = 0
o.mapper.random_seed = 0
o.triangulation.random_seed = 0
o.ba_refine_focal_length = not fix_f
o.ba_refine_principal_point = False
o.ba_refine_extra_params = model == "SIMPLE_RADIAL"
o.mapper.init_min_num_inliers = 30
o.mapper.init_min_tri_angle = 4.0
o.mapper.abs_pose_min_num_inliers = 15
o.triangulation.ignore_two_view_tracks = False
(work / "sparse").mkdir()
models = pycolmap.incremental_mapping(db, work / "img", work / "sparse", o)
r = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))


def ang(R):
    return np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


Rs = []
for n in names:
    im = r.find_image_with_name(n)
    cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
    Rs.append(np.asarray(cfw.rotation.matrix()).T)  # world_from_cam rotation
cam = next(iter(r.cameras.values()))


def rel(R, i, j):
    return R[i].T @ R[j]


Rg = [g[:3, :3] for g in gt]
print(
    scene,
    model,
    sys.argv[3],
    "params",
    np.round(cam.params, 4),
    "f_gt",
    round(float(f_gt), 1),
    "pts",
    r.num_points3D(),
    "rel err deg",
    [round(ang(rel(Rs, i, j).T @ rel(Rg, i, j)), 3) for i, j in ((0, 1), (0, 2), (1, 2))],
)
