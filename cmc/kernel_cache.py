"""What every compiled numba kernel (:mod:`cmc.mpi.plane_sampling`, :mod:`cmc.mpi.composite_kernel`,
:mod:`cmc.serving.texture_kernel`, :mod:`cmc.method.sweep_kernel`, :mod:`cmc.method.prior_kernel`)
shares: a writable on-disk cache, found before the first kernel is defined, and the threading of
parallel kernels (:data:`PARALLEL_LAUNCH`).

numba looks for a writable cache folder the moment a ``cache=True`` kernel is defined (at import)
and raises ``RuntimeError: cannot cache function ...`` when it finds none. It tries
``NUMBA_CACHE_DIR``, then ``__pycache__`` beside the module, then the user's cache folder
(``~/.cache/numba``). An installed package that is read-only for the user running it (another
user's environment, a container's read-only root filesystem, a read-only ``$HOME``) has none of
them; :func:`prepare` then points numba at a folder of this user's in the temporary directory.

Kernels compiled in advance: :func:`warm_up_kernels` compiles every kernel module's kernels
(:data:`KERNEL_MODULES`) into the cache; ``make install`` runs it, and so does each job before its
model build (``worker.pipeline``), which then loads them. ``CMC_KERNEL_CACHE_SEED`` names a cache
folder made by :func:`warm_up_kernels` run with ``NUMBA_CACHE_DIR`` pointing at it (the Docker
images do this at build time). It may be read-only: :func:`prepare` copies its files into the
cache folder in use, where they are missing, so a fresh process loads the kernels (0.5-0.6 s)
instead of compiling them (46-47 s on a 2-core machine of 2026-12-07). numba keys each entry by
the source file's path and content hash and by the CPU it was compiled for: a seed compiled on
another CPU model is ignored and the kernels compile once into the writable folder.
"""

from __future__ import annotations

import importlib
import os
import shutil
import tempfile
import threading
from pathlib import Path

import numba
from numba.misc.appdirs import AppDirs

# Parallel loops on OpenMP first: torch's CPU ops run on the same OpenMP threads in this process,
# so the kernels get the threads that torch's ops leave spinning, instead of competing with them
# (a pool of other threads ran the kernels 1.6x slower on two cores).
numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
# Held around every launch of a parallel kernel: numba's fallback layer (workqueue) aborts on
# launches from two threads at once, and two trainings in threads of one process share the cores
# anyway.
PARALLEL_LAUNCH = threading.Lock()

SEED_ENV = "CMC_KERNEL_CACHE_SEED"

# The modules that define numba kernels, each with a ``warm_up()`` that compiles all of them.
KERNEL_MODULES = (
    "cmc.mpi.plane_sampling",
    "cmc.mpi.composite_kernel",
    "cmc.method.sweep_kernel",
    "cmc.method.prior_kernel",
    "cmc.serving.texture_kernel",
)


def warm_up_kernels() -> None:
    """Compile every kernel of :data:`KERNEL_MODULES` into the on-disk cache, or load it from there
    where it is cached already (0.5-0.6 s on two cores; compiling them: 46-47 s), once per CPU
    model and cache folder."""
    for name in KERNEL_MODULES:
        importlib.import_module(name).warm_up()


def _writable(folder: Path) -> bool:
    """Whether ``folder`` can be made and written by this process (numba's own test)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def prepare() -> Path:
    """Make sure numba has a writable cache folder for the kernels of this package, seeded from
    ``CMC_KERNEL_CACHE_SEED`` when that is set (it needs ``NUMBA_CACHE_DIR``); returns the folder.

    Idempotent and safe in concurrent processes: each seed file is copied under a temporary name
    and renamed, the index files (``*.nbi``) after the data files (``*.nbc``) they point to."""
    seed = os.environ.get(SEED_ENV)
    if numba.config.CACHE_DIR:
        folder = Path(numba.config.CACHE_DIR)
        if not _writable(folder):
            raise RuntimeError(f"NUMBA_CACHE_DIR={folder} is not a writable folder: the compiled kernels need one")
    elif seed:
        raise RuntimeError(f"{SEED_ENV} is set without NUMBA_CACHE_DIR (the folder to copy the seed into)")
    else:
        for folder in (Path(__file__).resolve().parent / "__pycache__", Path(AppDirs("numba", False).user_cache_dir)):
            if _writable(folder):
                return folder
        folder = Path(tempfile.gettempdir()) / f"cmc-numba-cache-{os.getuid()}"
        if not _writable(folder):
            raise RuntimeError(f"no writable folder for the compiled kernels (tried {folder}): set NUMBA_CACHE_DIR")
        numba.config.CACHE_DIR = str(folder)
    if seed:
        _copy_missing(Path(seed), folder)
    return folder


def _copy_missing(seed: Path, folder: Path) -> None:
    """Copy the files of the cache folder ``seed`` that ``folder`` lacks, data before indexes."""
    if not seed.is_dir():
        raise RuntimeError(f"{SEED_ENV}={seed} is not a folder")
    files = sorted((p for p in seed.rglob("*") if p.is_file()), key=lambda p: p.suffix == ".nbi")
    for src in files:
        dst = folder / src.relative_to(seed)
        if dst.exists():
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=dst.parent, prefix=".seed-")
        os.close(fd)
        shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
