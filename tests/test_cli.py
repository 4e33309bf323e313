"""The ``cmc`` command line on tiny scene folders: train -> bake -> render, and clean errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from cmc.cli import main
from cmc.data.datasets import load_image, save_scene_folder, synthetic_scene
from cmc.geometry.cameras import CameraFile, save_camera_file


@pytest.fixture()
def scene_dir(tmp_path):
    return save_scene_folder(synthetic_scene(num_views=3, width=48, height=36), tmp_path / "scene")


def test_train_then_render(scene_dir, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", str(scene_dir), "--out", str(out), "--steps", "6", "--device", "cpu"]) == 0
    assert (out / "checkpoint.pt").exists() and (out / "baked" / "mpi.json").exists()
    info = json.loads((out / "train.json").read_text())
    assert info["steps"] == 6 and info["config"]["preset"] == "fast"
    # Running again resumes at the final checkpoint: nothing left to train.
    assert main(["train", str(scene_dir), "--out", str(out), "--steps", "6", "--device", "cpu"]) == 0
    assert json.loads((out / "train.json").read_text())["steps"] == 6
    renders = tmp_path / "renders"
    assert (
        main(["render", str(out / "baked"), "--cameras", str(scene_dir / "cameras.json"), "--out", str(renders)]) == 0
    )
    img = load_image(renders / "view000.png")
    assert img.shape == (36, 48, 3)
    depth = np.load(renders / "view000_depth.npy")
    assert depth.shape == (36, 48) and np.isfinite(depth).all() and (depth > 0).all()


def _expect_error(argv, capsys, *needles):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    for n in needles:
        assert n in err, err


def test_missing_cameras_file(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    _expect_error(["train", str(tmp_path / "empty"), "--out", str(tmp_path / "o")], capsys, "cameras file not found")


def test_images_of_different_sizes(scene_dir, tmp_path, capsys):
    from PIL import Image

    Image.new("RGB", (40, 30)).save(scene_dir / "view001.png")
    _expect_error(["train", str(scene_dir), "--out", str(tmp_path / "o")], capsys, "different sizes")


def test_one_view_is_not_enough(tmp_path, capsys):
    d = save_scene_folder(synthetic_scene(num_views=3, width=32, height=24).subset([0]), tmp_path / "one")
    _expect_error(["train", str(d), "--out", str(tmp_path / "o")], capsys, "at least 2 views")


@pytest.mark.parametrize(
    "edit, needle",
    [
        (lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")), "NaN"),
        (lambda d: [f.update(near=9.0, far=1.0) for f in d["frames"]], "near < far"),
        (lambda d: d["frames"][0].pop("transform_matrix"), "transform_matrix"),
        (lambda d: d.update(convention="directx"), "unknown pose convention"),
    ],
)
def test_malformed_cameras(scene_dir, tmp_path, capsys, edit, needle):
    path = scene_dir / "cameras.json"
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    _expect_error(["train", str(scene_dir), "--out", str(tmp_path / "o")], capsys, needle)


def test_cameras_without_bounds(scene_dir, tmp_path, capsys):
    from cmc.geometry.cameras import load_camera_file

    cf = load_camera_file(scene_dir / "cameras.json")
    save_camera_file(CameraFile(cf.cameras, cf.file_paths, None), scene_dir / "cameras.json")
    _expect_error(["train", str(scene_dir), "--out", str(tmp_path / "o")], capsys, "no near/far")


def test_render_needs_a_baked_folder(tmp_path, capsys):
    _expect_error(["render", str(tmp_path), "--cameras", "x.json", "--out", str(tmp_path / "r")], capsys, "mpi.json")


def test_bench_needs_lpips_weights(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("CMC_LPIPS_DIR", raising=False)
    _expect_error(["bench", "llff", "--data", str(tmp_path), "--out", str(tmp_path / "r.json")], capsys, "LPIPS")


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["synthetic", "--input-gains", "1,2"], "three factors"),
        (["synthetic", "--input-gains", "1,x,1"], "three factors"),
        (["synthetic", "--input-gains", "1,0,1"], "three factors"),
        (["llff", "--data", ".", "--input-gains", "1,1,1"], "for the synthetic benchmark"),
        (["synthetic", "--scenes", "cards", "--set", "model.plane_density_floor=0"], "plane_density_floor"),
    ],
)
def test_bench_refuses_bad_options(tmp_path, capsys, extra, message):
    args = ["bench", *extra, "--out", str(tmp_path / "r.json"), "--lpips-weights", str(tmp_path)]
    _expect_error(args, capsys, message)


def test_demo_runs_end_to_end(tmp_path):
    from cmc.demo import run_demo

    summary = run_demo(tmp_path / "demo", steps=40, width=64, height=48)
    for name in ("novel_view.png", "novel_depth.png", "novel_depth.npy", "orbit.gif", "baked/mpi.json"):
        assert (tmp_path / "demo" / name).exists(), name
    assert summary["novel_view_psnr_db"] > 20
    assert {"novel_view_psnr_db", "novel_depth_median_abs_rel_error"} <= summary["reading"].keys()
    # the depth map carries its legend: a colour ramp from near (yellow) to far (blue), then labels
    depth_png = np.asarray(Image.open(tmp_path / "demo" / "novel_depth.png"), dtype=np.float64) / 255
    assert depth_png.shape == (48 + 28, 64, 3)
    ramp = depth_png[48 + 5]
    assert ramp[0, 0] > 0.9 and ramp[0, 2] < 0.4 and ramp[-1, 2] > ramp[-1, 0]  # yellow, then blue
    assert depth_png[48 + 10 :].max() > 0.5  # the labels
    # The output holds what the summary lists (and the README names), nothing else (no checkpoint).
    listed = {name.rstrip("/") for name in summary["outputs"]} | {"summary.json"}
    assert {p.name for p in (tmp_path / "demo").iterdir()} == listed
    assert not list((tmp_path / "demo").rglob("*.pt"))


def test_bench_synthetic_reports_halfway_near_and_beyond_views(tmp_path, capsys):
    """A short run of the wide-baseline benchmark on one scene: the three kinds of view scored,
    with depth error, and one diagnostic sheet per test view (3 rows of tiles at 252x189)."""
    from tests.helpers import SHARED_DIR

    weights = SHARED_DIR / "weights"
    if not (weights / "lpips_alex.pth").exists():
        pytest.skip("LPIPS weights not in shared/")
    out = tmp_path / "syn.json"
    args = ["bench", "synthetic", "--scenes", "cards", "--steps", "2", "--out", str(out)]
    args += ["--lpips-weights", str(weights), "--save-dir", str(tmp_path / "runs"), "--set", "model.num_planes=8"]
    assert main(args) == 0
    report = json.loads(out.read_text())
    assert report["config"]["model"]["num_planes"] == 8
    (scene,) = report["scenes"]
    assert [v["kind"] for v in scene["views"]] == ["halfway"] * 3 + ["near"] * 3 + ["beyond"] * 3
    for kind in ("halfway", "near", "beyond"):
        assert 10 < scene[kind]["psnr"] < 50 and 0 <= scene[kind]["depth_rel_error"] < 1
    table = out.with_suffix(".md").read_text()
    assert "| cards | halfway |" in table and "| cards | beyond |" in table
    assert (tmp_path / "runs" / "fast" / "cards" / "cards_beyond2_sheet.png").exists()
    sheet = load_image(tmp_path / "runs" / "fast" / "cards" / "cards_half01_sheet.png")
    assert sheet.shape == (3 * 189, 5 * 252, 3)


def test_user_errors_are_cmc_errors_and_bugs_stay_bugs(tmp_path, capsys, monkeypatch):
    """The CLI reports CMCError (and missing files) as an error line; any other ValueError is a
    bug and propagates with its traceback."""
    import pytest

    import cmc.cli
    from cmc.errors import CMCError, ConfigError

    _expect_error(["export", str(tmp_path), "--out", str(tmp_path / "x.glb")], capsys, "mpi.json")
    monkeypatch.setattr(cmc.cli, "cmd_export", lambda args: (_ for _ in ()).throw(ConfigError("bad option")))
    _expect_error(["export", str(tmp_path), "--out", str(tmp_path / "x.glb")], capsys, "bad option")
    assert issubclass(ConfigError, CMCError) and issubclass(CMCError, ValueError)

    def bug(args):
        raise ValueError("a programming error")

    monkeypatch.setattr(cmc.cli, "cmd_export", bug)
    with pytest.raises(ValueError, match="a programming error"):
        main(["export", str(tmp_path), "--out", str(tmp_path / "x.glb")])


def test_bench_markdown_table_has_a_row_per_scene_then_the_mean():
    from cmc.eval.bench import markdown_table

    m = {"psnr": 23.236, "ssim": 0.75049, "lpips_alex": 0.1234, "lpips_vgg": 0.2101}
    m |= {"train_seconds": 440.4, "render_ms_median": 137.6}
    merge2 = {"psnr": 22.104, "ssim": 0.7, "lpips_alex": 0.2, "render_ms_median": 80.2}
    lines = markdown_table({"scenes": [{"scene": "fern", **m, "merge2": merge2}], "mean": m}).splitlines()
    assert lines[0].startswith("| scene | PSNR | SSIM | LPIPS-alex | LPIPS-vgg | train s | render ms | merged x2")
    assert lines[1] == "|---|---|---|---|---|---|---|---|"
    assert lines[2] == "| fern | 23.24 | 0.750 | 0.123 | 0.210 | 440 | 138 | 22.10 / 0.700 / 0.200 / 80 |"
    assert lines[3] == "| **mean** | 23.24 | 0.750 | 0.123 | 0.210 | 440 | 138 |  |"
