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

from typing import TYPE_CHECKING

from service.storage.base import Storage, StorageError, check_key, file_response
from service.storage.local import LocalStorage

if TYPE_CHECKING:
    from service.settings import Settings

__all__ = ["LocalStorage", "Storage", "StorageError", "check_key", "file_response", "open_storage"]


def open_storage(settings: Settings) -> Storage:
    """The storage the settings name: an S3 bucket (``CMC_STORAGE=s3://bucket/prefix``, checked
    to be reachable: StorageError otherwise) or the local folder ``resolved_storage_dir``.
    Working folders older than the longest job are removed."""
    storage: Storage
    if settings.storage:
        from service.storage.s3 import S3Storage

        storage = S3Storage.from_settings(settings)
        storage.check()
    else:
        storage = LocalStorage(settings.resolved_storage_dir)
    # an hour past the longest phase: past a video's hour too (worker.celery_app)
    storage.sweep_scratch(max(settings.poses_time_limit, settings.train_time_limit) + 3600)
    return storage
