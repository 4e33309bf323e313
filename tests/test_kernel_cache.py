"""The compiled kernels where the service is deployed: the package and ``$HOME`` read-only, run as
another user than the one who installed it (the Docker images' service user under compose's
``read_only: true``), with and without kernels compiled in advance (``cmc.kernel_cache``).

The package is a read-only copy of ``cmc/`` imported by a child process; as root the child runs as
``nobody`` (root writes read-only folders anyway), otherwise as this user.
"""

from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from cmc.kernel_cache import KERNEL_MODULES

ROOT = Path(__file__).resolve().parents[1]
INSTALL_SCRIPT = ROOT / "docker" / "install-service.sh"
NOBODY = 65534


def image_warm_up_code() -> str:
    """The Python code docker/install-service.sh runs to compile the kernels into the seed."""
    return re.search(r'python -c "([^"]+)"', INSTALL_SCRIPT.read_text())[1]


def _read_only(tree: Path) -> None:
    for p in [tree, *tree.rglob("*")]:
        p.chmod(stat.S_IRUSR | stat.S_IRGRP | stat.S_IROTH | (0o111 if p.is_dir() else 0))


@pytest.fixture
def place() -> Iterator[Path]:
    """A folder every user can reach (pytest's own tmp_path is private to this user)."""
    folder = Path(tempfile.mkdtemp(prefix="cmc-kernel-cache-"))
    folder.chmod(0o755)
    try:
        yield folder
    finally:
        for p in [folder, *folder.rglob("*")]:
            if p.is_dir():
                p.chmod(0o755)
        shutil.rmtree(folder)


@pytest.fixture
def install(place: Path) -> Path:
    """A read-only copy of the package, a read-only home and a writable temporary folder."""
    shutil.copytree(ROOT / "cmc", place / "site" / "cmc", ignore=shutil.ignore_patterns("__pycache__"))
    _read_only(place / "site")
    (place / "home").mkdir(mode=0o555)
    (place / "tmp").mkdir(mode=0o777)
    (place / "tmp").chmod(0o1777)
    return place


def run_child(place: Path, code: str, as_service_user: bool, **env: str) -> subprocess.CompletedProcess[str]:
    prefix = []
    if as_service_user and os.geteuid() == 0:
        prefix = ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups"]
    child_env = {
        "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
        "HOME": str(place / "home"),
        "TMPDIR": str(place / "tmp"),
        "PYTHONPATH": str(place / "site"),
        "PYTHONDONTWRITEBYTECODE": "1",
        **env,
    }
    return subprocess.run(
        [*prefix, sys.executable, "-c", code], env=child_env, capture_output=True, text=True, timeout=600, cwd=place
    )


def test_the_image_compiles_every_kernel_module() -> None:
    """The images' build step and ``make install`` compile the kernels of every module that
    defines one: the modules cmc.kernel_cache.warm_up_kernels goes through."""
    assert "warm_up_kernels()" in image_warm_up_code()
    assert "warm_up_kernels()" in (ROOT / "Makefile").read_text()
    defining = {
        ".".join(path.relative_to(ROOT).with_suffix("").parts)
        for path in (ROOT / "cmc").rglob("*.py")
        if "@numba.njit" in path.read_text()
    }
    assert defining == set(KERNEL_MODULES)


def test_kernels_import_and_compile_from_a_read_only_install(install: Path) -> None:
    """No writable folder beside the modules nor in $HOME: the kernels are defined (at import)
    and compiled into a folder of this user's in the temporary directory."""
    code = (
        "import cmc.serving.texture_kernel, cmc.mpi.plane_sampling as s; from cmc import kernel_cache; "
        "s.warm_up(); print(kernel_cache.prepare())"
    )
    r = run_child(install, code, as_service_user=True)
    assert r.returncode == 0, r.stderr
    folder = Path(r.stdout.strip().splitlines()[-1])
    assert folder.parent == install / "tmp"
    assert any(folder.rglob("plane_sampling.*.nbi")), "nothing was cached"


def test_kernels_compiled_in_advance_are_loaded_not_compiled(install: Path) -> None:
    """The images' recipe: compiled at build time into a seed that is read-only at run time, then
    imported by the service user with NUMBA_CACHE_DIR in /tmp: every kernel a cache hit."""
    seed = install / "seed"
    built = run_child(install, image_warm_up_code(), as_service_user=False, NUMBA_CACHE_DIR=str(seed))
    assert built.returncode == 0, built.stderr
    _read_only(seed)
    count = (
        "import numba, sys; from numba.core.registry import CPUDispatcher; "
        f"mods = [sys.modules[m] for m in {KERNEL_MODULES!r}]; "
        "ks = [v for m in mods for v in vars(m).values() if isinstance(v, CPUDispatcher)]; "
        "print(len(ks), sum(sum(k.stats.cache_hits.values()) for k in ks), "
        "sum(sum(k.stats.cache_misses.values()) for k in ks))"
    )
    env = {"NUMBA_CACHE_DIR": str(install / "tmp" / "numba-cache"), "CMC_KERNEL_CACHE_SEED": str(seed)}
    r = run_child(install, image_warm_up_code() + "; " + count, as_service_user=True, **env)
    assert r.returncode == 0, r.stderr
    kernels, hits, misses = map(int, r.stdout.split()[-3:])
    assert kernels >= 5 and hits > 0 and misses == 0, r.stdout


def test_a_seed_without_a_cache_folder_is_refused(install: Path) -> None:
    r = run_child(install, "import cmc.mpi.plane_sampling", as_service_user=True, CMC_KERNEL_CACHE_SEED="/nonexistent")
    assert r.returncode != 0 and "NUMBA_CACHE_DIR" in r.stderr
