"""The FastAPI application factory: ``uvicorn --factory service.app:create_app``.

``CMC_MODE=celery`` sends jobs to Celery workers through Redis (docker-compose);
``embedded`` (the default, used by ``cmc serve``) runs them in a thread of this process.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from importlib.metadata import entry_points
from typing import Any

from fastapi import FastAPI

from cmc.data.images import MemoryBudget
from service.api import Services, router
from service.auth import KeyRing
from service.db.scenes import SceneStore
from service.errors import install_error_handlers
from service.jobs import CeleryJobQueue, JobQueue
from service.limits import Limiter, MemoryLimiter, RedisLimiter
from service.metrics import Metrics, MetricsMiddleware
from service.middleware import BodyGuard, LocalOnly
from service.quotas import Quotas, RateLimitHeaders
from service.renders import BakedCache, RenderQueue
from service.settings import Settings, load_settings
from service.storage import Storage, open_storage

log = logging.getLogger("cmc.api")

# Threads that check uploaded photos (decodes wait there for the decode budget), apart from the thread
# pool of the other routes, so uploads waiting for memory never hold up status polls or probes.
INTAKE_THREADS = 4

DESCRIPTION = """Three photos of a scene in, a navigable 3D view out.

Upload photos (`POST /v1/scenes`), poll the job (`GET /v1/scenes/{id}`) until `ready`, then
render any camera (`POST /v1/scenes/{id}/render`, `/depth`) or fetch the baked MPI for
client-side rendering. Errors are always `{"error": {"code", "message", "details"}}`.
Cameras use the transforms.json shape with a `convention` field (`opengl`, ARKit's axes, or
`opencv`); intrinsics are in pixels with the image's top-left corner at (0, 0).
"""


def installed_runner() -> Callable[[SceneStore, Storage, Settings, MemoryBudget], Any]:
    """The in-process job runner worker/ registers under the ``cmc.job_runners`` entry point
    (pyproject.toml), found by name so that the API does not import the workers."""
    found = list(entry_points(group="cmc.job_runners", name="embedded"))
    if not found:
        raise RuntimeError("no embedded job runner is installed (pip install -e . registers worker.embedded)")
    return found[0].load()


def create_app(
    settings: Settings | None = None,
    queue: JobQueue | None = None,
    limiter: Limiter | None = None,
    embedded_runner: Callable[[SceneStore, Storage, Settings, MemoryBudget], Any] | None = None,
) -> FastAPI:
    """Build the app. Without ``queue``: Celery (``settings.mode == 'celery'``) or the embedded
    runner, ``embedded_runner(store, storage, settings, decode_memory)`` (``cmc serve`` passes
    ``worker.embedded.EmbeddedRunner``; default :func:`installed_runner`), a JobQueue started and
    stopped with the app's lifespan. Without ``limiter``: the quotas are counted in Redis (the
    broker) in celery mode, in memory embedded."""
    settings = settings or load_settings()
    store = SceneStore(settings.resolved_database_url, migrate=settings.migrate_on_start)
    storage = open_storage(settings)
    keys = KeyRing.load(settings.api_keys, settings.api_keys_file)
    decode_memory = MemoryBudget(settings.decode_memory_bytes)  # this process's photo decodes, jobs' included
    runner = None
    if queue is None:
        if settings.mode == "celery":
            queue = CeleryJobQueue.from_settings(settings)
        else:
            runner = (embedded_runner or installed_runner())(store, storage, settings, decode_memory)
            queue = runner
    metrics = Metrics(store, queue)
    if limiter is None:
        limiter = RedisLimiter(settings.broker_url) if settings.mode == "celery" else MemoryLimiter()
    quotas = Quotas(settings, limiter, not keys.open, lambda limit: metrics.rate_limited.labels(limit).inc())
    render_queue = RenderQueue(settings.render_concurrency, settings.render_queue)
    intake = ThreadPoolExecutor(INTAKE_THREADS, thread_name_prefix="cmc-intake")

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        if keys.open:
            log.warning("no API keys configured: requests are accepted without a key")
        if runner is not None:
            runner.start()
        try:
            yield
        finally:
            if runner is not None:
                runner.stop()
            render_queue.close()
            if isinstance(limiter, RedisLimiter):
                limiter.close()
            intake.shutdown(wait=False, cancel_futures=True)
            store.close()

    app = FastAPI(title="CMC reconstruction service", version="1.0.0", description=DESCRIPTION, lifespan=lifespan)
    renders = BakedCache(storage, settings.render_cache_bytes, settings.render_threads)
    app.state.services = Services(
        settings, store, storage, queue, keys, renders, metrics, render_queue, quotas, intake, decode_memory
    )
    install_error_handlers(app)
    app.add_middleware(RateLimitHeaders)
    app.add_middleware(BodyGuard, keys=keys, max_json_bytes=settings.max_json_bytes, streamed={("POST", "/v1/scenes")})
    if keys.open:
        app.add_middleware(LocalOnly, extra_hosts=set(settings.allowed_hosts.split(",")))
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.include_router(router)
    return app
