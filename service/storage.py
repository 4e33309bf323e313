"""Artifact storage: one interface, a local-filesystem implementation.

Artifacts of a scene live under keys ``{scene_id}/...``, every one named by
:class:`service.layout.SceneLayout`. Keys are built from scene ids (hex) and fixed names only;
:meth:`LocalStorage.path` refuses anything else, so no user-supplied name ever becomes a path.
In docker-compose the root is a volume shared by the API and the workers.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Protocol

_KEY = re.compile(r"^[0-9a-f]{32}(/[A-Za-z0-9][A-Za-z0-9._-]{0,99})*$")


class StorageError(ValueError):
    """A malformed key (never a user's name) or a missing artifact."""


class Storage(Protocol):
    """What the API and the pipeline need from artifact storage."""

    def path(self, key: str) -> Path:
        """A local path for ``key`` (tools such as COLMAP and torch need files); parents exist."""
        ...

    def write_bytes(self, key: str, data: bytes) -> None:
        """Write atomically: readers see the old or the new content, never a part."""
        ...

    def read_bytes(self, key: str) -> bytes: ...

    def exists(self, key: str) -> bool: ...

    def delete_scene(self, scene_id: str) -> None:
        """Remove every artifact of a scene (no error if there are none)."""
        ...

    def check(self) -> None:
        """Raise if the storage cannot be written (readiness probe)."""
        ...


class LocalStorage:
    """Artifacts as files under ``root`` (a volume shared by API and workers in docker-compose)."""

    def __init__(self, root: str | Path):
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        if not _KEY.match(key) or ".." in key:
            raise StorageError(f"invalid storage key {key!r}")
        p = self.root / key
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def write_bytes(self, key: str, data: bytes) -> None:
        p = self.path(key)
        fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=".tmp-")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.replace(tmp, p)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    def read_bytes(self, key: str) -> bytes:
        try:
            return self.path(key).read_bytes()
        except FileNotFoundError:
            raise StorageError(f"no artifact {key}") from None

    def exists(self, key: str) -> bool:
        return (self.root / key).exists() if _KEY.match(key) else False

    def delete_scene(self, scene_id: str) -> None:
        folder = self.path(scene_id)
        if folder.exists():
            # rename first so a half-deleted folder is never mistaken for a scene
            trash = self.root / f".deleted-{scene_id}-{uuid.uuid4().hex[:8]}"
            os.replace(folder, trash)
            shutil.rmtree(trash, ignore_errors=True)

    def check(self) -> None:
        probe = self.root / ".probe"
        probe.write_bytes(b"ok")
        probe.unlink()
