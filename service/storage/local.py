"""Artifacts as files in a local folder (:class:`LocalStorage`)."""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from service.storage.base import Storage, StorageError, check_key, is_key


class LocalStorage(Storage):
    """Artifacts as files under ``root`` (one host, or a volume every process mounts). Working
    folders are under ``root/.work``, on the same file system, so publishing is a rename."""

    def __init__(self, root: str | Path):
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        self.work_dir = self.root / ".work"

    def path(self, key: str) -> Path:
        """The local path of ``key``; its parent folders exist."""
        p = self.root / check_key(key)
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
        try:  # no folder is made for a read: one made mid-publish would race the rename
            return (self.root / check_key(key)).read_bytes()
        except (FileNotFoundError, IsADirectoryError):
            raise StorageError(f"no artifact {key}") from None

    def exists(self, key: str) -> bool:
        return (self.root / key).is_file() if is_key(key) else False

    def list(self, prefix: str) -> list[str]:
        folder = self.root / check_key(prefix)
        files = [p for p in folder.rglob("*") if p.is_file() and not p.name.startswith(".tmp-")]
        return sorted(p.relative_to(self.root).as_posix() for p in files)

    def delete(self, key: str) -> None:
        (self.root / check_key(key)).unlink(missing_ok=True)

    def delete_scene(self, scene_id: str) -> None:
        self._remove(self.path(scene_id))

    def _remove(self, p: Path) -> None:
        if p.is_dir():
            # rename first so a half-deleted folder is never mistaken for a complete one
            trash = self.root / f".deleted-{p.name}-{uuid.uuid4().hex[:8]}"
            os.replace(p, trash)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)

    def publish(self, key: str, src: Path, manifest: str | None = None) -> None:
        dst = self.path(key)
        if src.is_dir():
            self._remove(dst)  # a folder cannot be renamed over another one
        os.replace(src, dst)

    @contextmanager
    def reading(self, key: str) -> Iterator[Path]:
        yield self.path(key)

    def locate(self, key: str, media_type: str, filename: str | None = None) -> Path:
        return self.path(key)

    def check(self) -> None:
        probe = self.root / ".probe"
        probe.write_bytes(b"ok")
        probe.unlink()
