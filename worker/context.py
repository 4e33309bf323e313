"""What every job phase of a worker process shares (:class:`JobContext`)."""

from __future__ import annotations

import os
import socket
import threading
import uuid
from dataclasses import dataclass, field

from cmc.data.images import MemoryBudget
from service.db.scenes import SceneStore
from service.jobs import JobQueue
from service.settings import Settings
from service.storage import Storage


def new_worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"


@dataclass
class JobContext:
    """What a phase needs: the record store, artifact storage, the queue for the next phase."""

    store: SceneStore
    storage: Storage
    queue: JobQueue
    settings: Settings
    worker_id: str = field(default_factory=new_worker_id)
    shutdown: threading.Event = field(default_factory=threading.Event)  # set: stop jobs, keep them queued
    # The budget of photo decodes this process's jobs share (with its API's uploads, embedded);
    # None: unbounded.
    decode_memory: MemoryBudget | None = None
