"""The import rules between the three packages: ``cmc`` (the library) imports neither ``service``
nor ``worker``; ``service`` imports ``worker`` only in ``service/serve.py`` (the process entry that
injects the embedded runner), never in ``create_app``. Checked on the source and in a fresh
interpreter, so a lazy import inside a function counts too."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imported_packages(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_the_source_follows_the_import_rules() -> None:
    for path in sorted((ROOT / "cmc").rglob("*.py")):
        assert not {"service", "worker"} & _imported_packages(path), f"{path} imports service/ or worker/"
    for path in sorted((ROOT / "service").rglob("*.py")):
        if path.name != "serve.py":
            assert "worker" not in _imported_packages(path), f"{path} imports worker/"


def _modules_after(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    return set(out.stdout.split())


def test_importing_the_library_loads_no_service_code() -> None:
    loaded = _modules_after(
        "import pkgutil, importlib, sys, cmc\n"
        "for m in pkgutil.walk_packages(cmc.__path__, 'cmc.'):\n"
        "    importlib.import_module(m.name)\n"
        "print(*sys.modules)"
    )
    assert "cmc.cli" in loaded and "cmc.poses.sfm" in loaded
    assert not {m for m in loaded if m.split(".")[0] in ("service", "worker")}


def test_create_app_loads_no_worker_code(tmp_path: Path) -> None:
    loaded = _modules_after(
        "import sys\n"
        "from service.app import create_app\n"
        "from service.settings import load_settings\n"
        "class NoJobs:\n"
        "    def submit(self, *a): pass\n"
        "    def ping(self): pass\n"
        f"settings = load_settings(data_dir={str(tmp_path)!r}, mode='embedded', api_keys='', api_keys_file=None)\n"
        "create_app(settings, queue=NoJobs())\n"
        "print(*sys.modules)"
    )
    assert "service.app" in loaded and "service.api.views" in loaded
    assert not {m for m in loaded if m.split(".")[0] == "worker"}
