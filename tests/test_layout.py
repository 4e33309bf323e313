"""One artifact layout (service.layout): every key of a scene is one storage accepts and stays
inside the scene's folder; our stored photo names map back to the client's; no code outside
LocalStorage asks for a stored file's path."""

from __future__ import annotations

import re
import uuid
from pathlib import Path

import pytest

from service.layout import ClientNames, SceneLayout
from service.storage import LocalStorage


def test_every_key_is_a_valid_storage_key_of_the_scene(tmp_path) -> None:
    sid = uuid.uuid4().hex
    layout, storage = SceneLayout(sid), LocalStorage(tmp_path)
    keys = [
        layout.uploads,
        layout.upload("00.jpg"),
        layout.cameras_upload,
        layout.scene_dir,
        layout.cameras,
        layout.checkpoint,
        layout.baked(),
        layout.baked("mpi_00.png"),
        layout.manifest,
        layout.export_glb(2),
        layout.video("orbit"),
        layout.preview(0),
        layout.preview(30),
    ]
    assert len(set(keys)) == len(keys)
    for key in keys:
        assert storage.path(key).is_relative_to(storage.path(sid)), key
    # the previews' folders and files, of any step, and nothing else of the scene or of another
    previews = [k for k in keys if layout.is_preview(k)]
    assert previews == [layout.preview(0), layout.preview(30)]
    assert layout.is_preview(f"{layout.preview(30)}/mpi.json") and layout.is_preview(f"{sid}/preview/mpi.json")
    assert not SceneLayout(uuid.uuid4().hex).is_preview(layout.preview(0))
    assert layout.manifest == f"{sid}/baked/mpi.json" and layout.video("orbit") == f"{sid}/videos/orbit.mp4"


def test_client_names() -> None:
    names = ClientNames(["00.jpg", "01.heic"], ["IMG_1.JPG", "garden shot.heic"])
    assert names.of("images/01.png") == "garden shot.heic" and names.of("00.jpg") == "IMG_1.JPG"
    assert names.of("other.png") == "other.png"
    assert names.in_text("00.jpg and 01.heic differ") == "IMG_1.JPG and garden shot.heic differ"


def test_artifacts_are_reached_through_reading_and_writing_only() -> None:
    """Outside LocalStorage no code asks storage for a path (S3 has none): it goes through
    ``reading`` / ``writing`` / ``publish``, with keys from SceneLayout."""
    root = Path(__file__).resolve().parents[1]
    for path in sorted([*(root / "service").rglob("*.py"), *(root / "worker").rglob("*.py")]):
        if path.parent.name != "storage":
            assert not re.search(r"storage\.path\(", path.read_text()), f"{path} uses storage.path()"


def test_preview_shares_from_the_environment(monkeypatch) -> None:
    """``CMC_PREVIEW_AT``: shares of the training steps, comma- or space-separated, or one number;
    empty for none; sorted, each at least 0."""
    from service.settings import load_settings

    assert load_settings().preview_at == [0.0, 0.1]
    for value, shares in (("0", [0.0]), ("0.2, 0.05", [0.05, 0.2]), ("0.1 0.1", [0.1]), ("", [])):
        monkeypatch.setenv("CMC_PREVIEW_AT", value)
        assert load_settings().preview_at == shares, value
    for bad in ("x", "-0.1"):
        monkeypatch.setenv("CMC_PREVIEW_AT", bad)
        with pytest.raises(ValueError):
            load_settings()
