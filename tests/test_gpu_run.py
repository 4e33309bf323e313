"""The Python that bench/gpu_run.sh runs on a lent GPU machine imports with the method's packages
alone: that machine has torch, numpy, numba and pillow, not the service's packages (sqlalchemy,
fastapi, celery, ...), and a script that reaches into ``service`` or ``worker`` fails there after
minutes of start-up (bench/profile_job.py did, through a constant it took from the worker)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}

# Packages a lent GPU machine does not have, and the project's own packages that need them.
ABSENT = ("service", "worker", "sqlalchemy", "fastapi", "starlette", "celery", "redis", "uvicorn", "boto3")

IMPORT_ALL = """
import importlib.abc, importlib.util, sys
absent = set(sys.argv[1].split(","))
class Absent(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in absent:
            raise ImportError(f"no module named {name!r} on a lent GPU machine")
sys.meta_path.insert(0, Absent())
for target in sys.argv[2:]:
    if target.endswith(".py"):
        spec = importlib.util.spec_from_file_location("script", target)
        spec.loader.exec_module(importlib.util.module_from_spec(spec))
    else:
        importlib.import_module(target)
"""


def gpu_run_targets() -> list[str]:
    """The scripts (``bench/*.py``) and modules (``-m``) bench/gpu_run.sh runs with Python."""
    text = (ROOT / "bench" / "gpu_run.sh").read_text()
    scripts = sorted(set(re.findall(r"python3 (bench/\w+\.py)", text)))
    modules = sorted(set(re.findall(r"python3 -m ([\w.]+)", text)) - {"pytest"})
    return scripts + modules


def test_gpu_run_finds_its_scripts() -> None:
    targets = gpu_run_targets()
    assert {"bench/gpudata.py", "bench/profile_job.py", "bench/explore_gpu.py", "cmc.cli"} <= set(targets)


def import_without_the_service(*targets: str) -> subprocess.CompletedProcess:
    """Import ``targets`` (script paths or module names) in a fresh Python where the packages of
    ``ABSENT`` cannot be imported."""
    args = [sys.executable, "-c", IMPORT_ALL, ",".join(ABSENT), *targets]
    return subprocess.run(args, cwd=ROOT, capture_output=True, text=True, env=ENV, timeout=300)


def test_gpu_run_scripts_import_without_the_service_packages() -> None:
    done = import_without_the_service(*gpu_run_targets(), "tests/test_cuda.py")
    assert done.returncode == 0, done.stderr[-3000:]


def test_the_check_catches_a_service_import(tmp_path: Path) -> None:
    script = tmp_path / "uses_worker.py"
    script.write_text("from worker.pipeline import JobStopped\n")
    done = import_without_the_service(str(script))
    assert done.returncode != 0 and "on a lent GPU machine" in done.stderr
