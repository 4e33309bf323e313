"""The import rules between the three packages: ``cmc`` (the library) imports neither ``service``
nor ``worker``; ``service`` imports ``worker`` only in ``service/serve.py`` (the process entry that
injects the embedded runner), never in ``create_app``; and ``create_app`` loads no torch (the
API loads it on its first render only, README "API"; ``cmc.config``, where the upload schema
reads the presets, is torch-free). Checked on the source and in a fresh interpreter, so a lazy
import inside a function counts too; and no module imports itself through others (an import
circle)."""

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


def test_create_app_loads_no_worker_code_and_no_torch(tmp_path: Path) -> None:
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
    assert "cmc.config" in loaded and "torch" not in loaded


def test_the_eta_and_the_presets_load_no_torch() -> None:
    """The API's status answers estimate with ``cmc.method.eta`` and the presets' step counts."""
    loaded = _modules_after("import sys, cmc.method.eta, cmc.config\nprint(*sys.modules)")
    assert "cmc.method.eta" in loaded and "torch" not in loaded


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports anywhere in its source (lazy imports too; a
    ``from package import name`` counts as the submodule when ``name`` is one)."""
    paths = {_module_name(p): p for pkg in ("cmc", "service", "worker") for p in (ROOT / pkg).rglob("*.py")}

    def known(name: str) -> str | None:
        while name and name not in paths:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for module, path in paths.items():
        targets: set[str | None] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {known(a.name) for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                package = module.split(".")[: len(module.split(".")) - (path.name != "__init__.py")]
                base = ".".join(package[: len(package) - node.level + 1]) if node.level else ""
                source = ".".join(p for p in (base, node.module or "") if p)
                for a in node.names:
                    sub = f"{source}.{a.name}"
                    targets.add(sub if sub in paths else known(source))
        graph[module] = {t for t in targets if t and t != module}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles: strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_module_imports_itself_through_others() -> None:
    graph = _import_graph()
    assert {"service.db.scenes", "worker.pipeline", "cmc.method.training"} <= graph.keys()
    assert "service.db.rows" in graph["service.db.scenes"]  # the graph sees imports
    assert _circles(graph) == []


def test_the_circle_finder_finds_a_circle() -> None:
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []


# The rooms of cmc/ (ARCHITECTURE.md), lowest first: a module imports only from its own room and
# the rooms before it.
CMC_ROOMS = [
    ["errors", "kernel_cache"],
    ["config"],
    ["geometry"],
    ["data"],
    ["poses", "mpi"],
    ["method"],
    ["serving"],
    ["eval"],
    ["demo"],
    ["cli"],
]


def test_cmc_rooms_import_only_from_the_rooms_below() -> None:
    level = {room: k for k, rooms in enumerate(CMC_ROOMS) for room in rooms}
    graph = _import_graph()
    rooms = {m.split(".")[1] for m in graph if m.startswith("cmc.") and m.count(".") >= 1}
    assert rooms == set(level), f"rooms without a place in CMC_ROOMS: {rooms ^ set(level)}"
    upward = [
        (m, t)
        for m, targets in graph.items()
        if m.startswith("cmc.")
        for t in targets
        if t.startswith("cmc.") and t.count(".") >= 1 and level[t.split(".")[1]] > level[m.split(".")[1]]
    ]
    assert upward == []
