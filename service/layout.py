"""Where a scene's artifacts live in storage, and the client's names for our stored photos.

:class:`SceneLayout` owns every storage key of a scene (``{scene_id}/...``): the uploads under
our own names, the scene folder the worker writes (working images + cameras.json), the training
checkpoint, the baked ``cmc-mpi`` folder and its preview, glTF exports and camera-path videos. Keys are built
from the scene id (hex) and fixed names only (storage refuses anything else).
:class:`ClientNames` turns our stored names back into the names the client uploaded.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

PREVIEW_PREFIX = "preview-"  # a preview's folder: this and its training step (SceneLayout.preview)
CAMERAS_UPLOAD = "cameras.json"  # the client's cameras file among the uploads (SceneLayout.cameras_upload)


@dataclass(frozen=True)
class SceneLayout:
    """The storage keys of scene ``scene_id``."""

    scene_id: str

    @property
    def uploads(self) -> str:
        """The folder of the uploads (the API publishes it whole, the worker reads it whole)."""
        return f"{self.scene_id}/uploads"

    def upload(self, name: str) -> str:
        """An uploaded file under our storage name (``00.jpg``, ``cameras.json``, ...)."""
        return f"{self.uploads}/{name}"

    @property
    def cameras_upload(self) -> str:
        """The client's cameras file, its frames renamed to our storage names."""
        return self.upload(CAMERAS_UPLOAD)

    @property
    def scene_dir(self) -> str:
        """The scene folder pose estimation writes and training reads."""
        return f"{self.scene_id}/scene"

    @property
    def cameras(self) -> str:
        """The estimated (or the client's) cameras with near/far, working resolution."""
        return f"{self.scene_dir}/cameras.json"

    @property
    def checkpoint(self) -> str:
        return f"{self.scene_id}/checkpoint.pt"

    def baked(self, name: str | None = None) -> str:
        """The baked folder, or the file ``name`` in it (``mpi.json``, an atlas)."""
        return f"{self.scene_id}/baked" + (f"/{name}" if name else "")

    @property
    def manifest(self) -> str:
        return self.baked("mpi.json")

    def preview(self, step: int) -> str:
        """The baked folder of the preview a job bakes at training step ``step`` (the same format
        as :meth:`baked`; a later preview is another folder, so that no reader sees one replaced
        file by file)."""
        return f"{self.scene_id}/{PREVIEW_PREFIX}{step}"

    def is_preview(self, key: str) -> bool:
        """Whether storage key ``key`` is a preview's folder or a file in it (any step)."""
        parts = key.split("/")
        return len(parts) > 1 and parts[0] == self.scene_id and parts[1].startswith("preview")

    def export_glb(self, mpi: int) -> str:
        """The glTF export of MPI ``mpi``."""
        return f"{self.scene_id}/exports/mpi_{mpi:02d}.glb"

    def video(self, path: str) -> str:
        """The camera-path video ``path`` (spiral, orbit, dolly)."""
        return f"{self.scene_id}/videos/{path}.mp4"


@dataclass(frozen=True)
class ClientNames:
    """Our stored upload names (``stored``) and the client's names for them (``client``), in the
    same order; the working images are named after the stored names' stems."""

    stored: Sequence[str]
    client: Sequence[str]

    def of(self, path: str) -> str:
        """The client's name of a stored upload or a working image made from it (by stem, any
        folder ignored); other names unchanged."""
        stem = path.rsplit("/", 1)[-1].rsplit(".", 1)[0]
        by_stem = {f.rsplit(".", 1)[0]: name for f, name in zip(self.stored, self.client, strict=True)}
        return by_stem.get(stem, path)

    def in_text(self, message: str) -> str:
        """``message`` with every stored upload name replaced by the client's (error messages)."""
        for ours, theirs in zip(self.stored, self.client, strict=True):
            message = message.replace(ours, theirs)
        return message
