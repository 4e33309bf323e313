"""Artifact storage: one interface, two implementations (a local folder, an S3 bucket).

Artifacts of a scene live under keys ``{scene_id}/...``, every one named by
:class:`service.layout.SceneLayout`. Keys are built from scene ids (hex) and fixed names only;
:func:`check_key` refuses anything else, so no user-supplied name ever becomes a path or an
object name.

Tools such as COLMAP, torch and ffmpeg need files, so code that works on artifacts does it in a
local working folder with explicit transfers at the boundaries, one mechanism for every artifact:
:meth:`Storage.reading` (a local copy of a file or folder for the duration of a ``with``) and
:meth:`Storage.writing` (a local place to write, published on a clean exit; or
:meth:`Storage.publish` for a file written again and again, such as a checkpoint). On local
storage both are the stored paths themselves (no copy) and publishing is a rename. Publishing
is atomic enough: readers see the old or the new file, never a part; a folder's files are all
in place before its ``manifest`` is (S3 has no atomic folder rename, so readers look for the
manifest). :func:`open_storage` picks the implementation from the settings (``CMC_STORAGE``).
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from starlette.responses import Response

    from service.settings import Settings

_KEY = re.compile(r"^[0-9a-f]{32}(/[A-Za-z0-9][A-Za-z0-9._-]{0,99})*$")


class StorageError(ValueError):
    """A malformed key (never a user's name), a missing artifact, or storage that cannot be used."""


def check_key(key: str) -> str:
    """``key`` if it is a storage key (a scene id, then fixed names); StorageError otherwise."""
    if not _KEY.match(key) or ".." in key:
        raise StorageError(f"invalid storage key {key!r}")
    return key


class Storage(ABC):
    """What the API and the pipeline need from artifact storage (keys: see the module)."""

    work_dir: Path  # local working folders (:meth:`scratch`)

    @abstractmethod
    def write_bytes(self, key: str, data: bytes) -> None:
        """Write atomically: readers see the old or the new content, never a part."""

    @abstractmethod
    def read_bytes(self, key: str) -> bytes:
        """The content of a file; StorageError if there is none."""

    @abstractmethod
    def exists(self, key: str) -> bool:
        """Whether a file is stored at ``key``."""

    @abstractmethod
    def list(self, prefix: str) -> list[str]:
        """Keys of the files under the folder ``prefix``, sorted."""

    @abstractmethod
    def delete(self, key: str) -> None:
        """Remove one file (no error if there is none)."""

    @abstractmethod
    def delete_scene(self, scene_id: str) -> None:
        """Remove every artifact of a scene (no error if there are none)."""

    @abstractmethod
    def publish(self, key: str, src: Path, manifest: str | None = None) -> None:
        """Store the local file or folder ``src`` at ``key`` (replacing what was there), taking
        it: ``src`` may be gone afterwards. A folder's ``manifest`` (a file name in it) is
        published after every other file."""

    @abstractmethod
    def reading(self, key: str) -> AbstractContextManager[Path]:
        """A local path holding the file or folder at ``key`` (a path that does not exist when
        nothing is stored there), valid inside the ``with``; never written to."""

    @abstractmethod
    def locate(self, key: str, media_type: str, filename: str | None = None) -> str | Path:
        """Where a client gets a stored file: a presigned URL (S3, which the API redirects to;
        answered with ``media_type`` and, with ``filename``, as an attachment) or the file
        itself (local storage, which the API sends)."""

    @abstractmethod
    def check(self) -> None:
        """Raise if the storage cannot be written (at start, and in the readiness probe)."""

    @contextmanager
    def scratch(self) -> Iterator[Path]:
        """An empty local working folder, removed after the ``with``."""
        self.work_dir.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=self.work_dir))
        try:
            yield tmp
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def sweep_scratch(self, older_than_s: float) -> list[Path]:
        """Remove the working folders untouched for ``older_than_s`` (left by a process that
        was killed: longer than any job may run, so none in use). Returns those removed."""
        if not self.work_dir.is_dir():
            return []
        cutoff = time.time() - older_than_s
        old = [p for p in self.work_dir.iterdir() if p.is_dir() and p.stat().st_mtime < cutoff]
        for p in old:
            shutil.rmtree(p, ignore_errors=True)
        return old

    @contextmanager
    def writing(self, key: str, manifest: str | None = None) -> Iterator[Path]:
        """A local path (parent folder existing, nothing there yet) to write a file or folder
        at, published at ``key`` when the ``with`` ends without an exception, dropped otherwise."""
        with self.scratch() as tmp:
            path = tmp / key.rsplit("/", 1)[-1]
            yield path
            self.publish(key, path, manifest)


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
        return (self.root / key).is_file() if _KEY.match(key) else False

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


def open_storage(settings: Settings) -> Storage:
    """The storage the settings name: an S3 bucket (``CMC_STORAGE=s3://bucket/prefix``, checked
    to be reachable: StorageError otherwise) or the local folder ``resolved_storage_dir``.
    Working folders older than the longest job are removed."""
    storage: Storage
    if settings.storage:
        from service.s3storage import S3Storage

        storage = S3Storage.from_settings(settings)
        storage.check()
    else:
        storage = LocalStorage(settings.resolved_storage_dir)
    # an hour past the longest phase: past a video's hour too (worker.celery_app)
    storage.sweep_scratch(max(settings.poses_time_limit, settings.train_time_limit) + 3600)
    return storage


def file_response(
    storage: Storage, key: str, media_type: str, filename: str | None = None, headers: dict[str, str] | None = None
) -> Response:
    """The answer to a download of a stored file: on S3, 307 to a presigned URL (the client
    gets the bytes straight from the bucket); on local storage, the file itself."""
    from starlette.responses import FileResponse, RedirectResponse

    headers = dict(headers or {})
    if filename is not None:
        headers["Content-Disposition"] = f'attachment; filename="{filename}"'
    where = storage.locate(key, media_type, filename)
    if isinstance(where, str):
        return RedirectResponse(where, status_code=307, headers=headers)
    return FileResponse(where, media_type=media_type, headers=headers)
