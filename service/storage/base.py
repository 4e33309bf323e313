"""The storage interface every implementation follows, the key rule, and the download answer
(see :mod:`service.storage` for keys and the transfer mechanism)."""

from __future__ import annotations

import re
import shutil
import tempfile
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from starlette.responses import Response

_KEY = re.compile(r"^[0-9a-f]{32}(/[A-Za-z0-9][A-Za-z0-9._-]{0,99})*$")


class StorageError(ValueError):
    """A malformed key (never a user's name), a missing artifact, or storage that cannot be used."""


def is_key(key: str) -> bool:
    """Whether ``key`` is a storage key: a scene id, then fixed names."""
    return bool(_KEY.match(key)) and ".." not in key


def check_key(key: str) -> str:
    """``key`` if it is a storage key (:func:`is_key`); StorageError otherwise."""
    if not is_key(key):
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
