"""docker-compose.yml, docker/ and .env.example, checked without a Docker engine.

Parses the compose file (PyYAML, with compose's ``${...}`` interpolation done here), the
Dockerfiles and .env.example, and checks them against the code they start: every CMC_* variable
is a field of service.settings.Settings, the commands name importable entry points, the Celery
routes send each task to a queue that some worker consumes, the API and the workers share the
artifact bucket (MinIO), the database and the broker but no volume, and the images install what
pyproject.toml pins.
When the ``docker compose`` plugin is installed, ``docker compose config`` validates the file too.
"""

from __future__ import annotations

import fnmatch
import importlib
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import urlsplit

import pytest
import yaml

from service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
ENV_EXAMPLE = ROOT / ".env.example"
DOCKERFILES = {"cpu": ROOT / "docker" / "Dockerfile", "gpu": ROOT / "docker" / "Dockerfile.gpu"}
INSTALL_SCRIPT = ROOT / "docker" / "install-service.sh"
APP_SERVICES = ("api", "worker-cpu", "worker-gpu", "worker-webhooks")
SECRETS = {
    "CMC_API_KEYS": "test-key-1,test-key-2",
    "POSTGRES_PASSWORD": "pw0123456789",
    "MINIO_ROOT_PASSWORD": "s3pw0123",
}


# -- compose's variable interpolation ----------------------------------------------------------


class InterpolationError(ValueError):
    """What compose reports for ``${VAR:?message}`` when VAR is unset or empty."""


_SUBST = re.compile(
    r"\$(?:(?P<escaped>\$)"
    r"|\{(?P<braced>[A-Za-z_][A-Za-z0-9_]*)(?:(?P<op>:?[-?+])(?P<arg>[^}]*))?\}"
    r"|(?P<named>[A-Za-z_][A-Za-z0-9_]*))"
)


def interpolate(value: Any, env: dict[str, str]) -> Any:
    """Compose's substitution in every string of ``value``: $$, $VAR, ${VAR}, ${VAR:-default},
    ${VAR-default}, ${VAR:?error}, ${VAR?error}, ${VAR:+alt}, ${VAR+alt}."""
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def sub(m: re.Match[str]) -> str:
        if m["escaped"]:
            return "$"
        name = m["braced"] or m["named"]
        op, arg = m["op"], m["arg"]
        is_set = name in env
        nonempty = bool(env.get(name))
        if op in (":-", "-"):
            use_default = not nonempty if op == ":-" else not is_set
            return arg if use_default else env[name]
        if op in (":?", "?"):
            if not (nonempty if op == ":?" else is_set):
                raise InterpolationError(f"{name}: {arg}")
            return env[name]
        if op in (":+", "+"):
            return arg if (nonempty if op == ":+" else is_set) else ""
        return env.get(name, "")

    return _SUBST.sub(sub, value)


def referenced_variables(text: str) -> set[str]:
    """Names of the variables the compose text substitutes ($$ is an escape, not a variable)."""
    names = set()
    for m in _SUBST.finditer(text):
        if not m["escaped"]:
            names.add(m["braced"] or m["named"])
    return names


def read_env_file(path: Path) -> dict[str, str]:
    env = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key, sep, value = line.partition("=")
        assert sep, f"{path.name}: not KEY=VALUE: {line!r}"
        value = value.strip()
        if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
            value = value[1:-1]
        env[key.strip()] = value
    return env


def load_compose(env_file: bool = True, **overrides: str) -> dict[str, Any]:
    """The compose file as `docker compose --env-file .env.example` sees it (or with no env file:
    the file's own defaults), with ``overrides`` (the shell environment, which takes precedence
    over the env file)."""
    raw = yaml.safe_load(COMPOSE.read_text())
    return interpolate(raw, {**(read_env_file(ENV_EXAMPLE) if env_file else {}), **overrides})


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return load_compose(**SECRETS)


@pytest.fixture(scope="module")
def services(compose: dict[str, Any]) -> dict[str, Any]:
    return compose["services"]


def environment(service: dict[str, Any]) -> dict[str, str]:
    env = service.get("environment", {})
    if isinstance(env, list):
        env = dict(item.split("=", 1) for item in env)
    return {k: "" if v is None else str(v) for k, v in env.items()}


def command(service: dict[str, Any]) -> list[str]:
    cmd = service["command"]
    return shlex.split(cmd) if isinstance(cmd, str) else [str(c) for c in cmd]


def duration_s(text: str) -> float:
    """Seconds of a compose duration such as ``30s``, ``1m30s`` or ``500ms``."""
    units = {"h": 3600.0, "m": 60.0, "s": 1.0, "ms": 0.001}
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|h|m|s)", text)
    assert parts and "".join(n + u for n, u in parts) == text, text
    return sum(float(n) * units[u] for n, u in parts)


def option(cmd: list[str], *names: str) -> list[str]:
    """Every value given to one of the options ``names`` (``-Q cpu`` or ``--queues=cpu``)."""
    values = []
    for i, arg in enumerate(cmd):
        for name in names:
            if arg == name and i + 1 < len(cmd):
                values.append(cmd[i + 1])
            elif name.startswith("--") and arg.startswith(name + "="):
                values.append(arg.split("=", 1)[1])
    return values


def healthcheck_shell(service: dict[str, Any]) -> str:
    test = service["healthcheck"]["test"]
    if isinstance(test, str):
        return test
    kind, *rest = test
    assert kind in ("CMD", "CMD-SHELL"), test
    return " ".join(rest) if kind == "CMD-SHELL" else shlex.join(rest)


def worker_queues(service: dict[str, Any]) -> set[str]:
    return {q for v in option(command(service), "-Q", "--queues") for q in v.split(",")}


# -- Dockerfiles -------------------------------------------------------------------------------


def dockerfile_instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) in order, continuation lines joined, comments dropped."""
    out, buf = [], ""
    for line in path.read_text().splitlines():
        if line.lstrip().startswith("#"):
            continue
        if line.rstrip().endswith("\\"):
            buf += line.rstrip()[:-1]
            continue
        buf += line
        if buf.strip():
            word, _, rest = buf.strip().partition(" ")
            out.append((word.upper(), rest.strip()))
        buf = ""
    return out


def dockerfile_args(path: Path) -> dict[str, str]:
    args = {}
    for ins, rest in dockerfile_instructions(path):
        if ins == "ARG":
            name, _, default = rest.partition("=")
            args[name] = default.strip('"')
    return args


def pyproject() -> dict[str, Any]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def torch_pin() -> str:
    pins = [d for d in pyproject()["dependencies"] if re.match(r"torch\s*==", d)]
    assert len(pins) == 1, pins
    return pins[0].replace(" ", "")


# -- the services ------------------------------------------------------------------------------


def test_services_exist(services: dict[str, Any]) -> None:
    one_shots = {"migrate", "minio-init"}
    assert {"redis", "db", "minio", "api", "worker-cpu", "worker-gpu", "worker-webhooks"} | one_shots <= set(services)


def test_every_variable_compose_reads_is_in_env_example_and_back() -> None:
    used = referenced_variables(COMPOSE.read_text())
    listed = set(read_env_file(ENV_EXAMPLE))
    assert used - listed == set(), "compose reads variables .env.example does not list"
    assert listed - used == set(), ".env.example lists variables compose never reads"


def test_every_cmc_variable_is_a_settings_field(services: dict[str, Any]) -> None:
    fields = {"CMC_" + name.upper() for name in Settings.model_fields}
    names = {k for s in services.values() for k in environment(s) if k.startswith("CMC_")}
    names |= {k for k in read_env_file(ENV_EXAMPLE) if k.startswith("CMC_")}
    assert names, "no CMC_* variable found"
    assert names - fields == set(), f"not fields of service.settings.Settings: {sorted(names - fields)}"


@pytest.mark.parametrize("missing", sorted(SECRETS))
def test_compose_refuses_to_start_without_secrets(missing: str) -> None:
    # .env.example leaves the secrets empty: a copied, unedited .env must not start anything
    assert read_env_file(ENV_EXAMPLE)[missing] == ""
    others = {k: v for k, v in SECRETS.items() if k != missing}
    with pytest.raises(InterpolationError, match=missing):
        load_compose(**others)
    with pytest.raises(InterpolationError, match=missing):
        load_compose(**others, **{missing: ""})


def test_api_keys_only_where_needed(services: dict[str, Any]) -> None:
    assert environment(services["api"])["CMC_API_KEYS"] == SECRETS["CMC_API_KEYS"]
    for name in ("worker-cpu", "worker-gpu", "worker-webhooks"):
        assert "CMC_API_KEYS" not in environment(services[name])


@pytest.mark.parametrize("env_file", [True, False], ids=["env-example", "defaults"])
@pytest.mark.parametrize("name", APP_SERVICES)
def test_settings_validate(monkeypatch: pytest.MonkeyPatch, name: str, env_file: bool) -> None:
    """The service's environment (from .env.example, or from the compose file's defaults alone),
    read by Settings exactly as at start: types and checks pass."""
    service = load_compose(env_file, **SECRETS)["services"][name]
    for key in list(os.environ):
        if key.startswith("CMC_"):
            monkeypatch.delenv(key)
    for key, value in environment(service).items():
        monkeypatch.setenv(key, value)
    from service.settings import load_settings

    s = load_settings()
    assert s.mode == "celery", "jobs would run inside the API process"
    assert s.broker_url and s.database_url
    assert s.storage.startswith("s3://") and s.s3_endpoint_url, "artifacts would need a shared volume"


def test_api_command_names_a_factory(services: dict[str, Any]) -> None:
    cmd = command(services["api"])
    assert cmd[0] == "uvicorn"
    assert "--factory" in cmd
    targets = [a for a in cmd[1:] if ":" in a and not a.startswith("-")]
    assert len(targets) == 1, cmd
    module, attr = targets[0].split(":")
    factory = getattr(importlib.import_module(module), attr)
    assert callable(factory)
    assert option(cmd, "--host") == ["0.0.0.0"], "the API must listen on the container's interfaces"
    port = option(cmd, "--port")
    assert len(port) == 1
    published = [str(p).rsplit(":", 1)[-1] for p in services["api"]["ports"]]
    assert published == port, "the published container port is not the one uvicorn listens on"
    assert f"127.0.0.1:{port[0]}/readyz" in healthcheck_shell(services["api"])
    # a stop cancels requests still running (what they staged is removed: test_service_integration)
    # before Docker's SIGKILL would leave it behind
    graceful = option(cmd, "--timeout-graceful-shutdown")
    assert graceful and float(graceful[0]) + 5 <= duration_s(services["api"].get("stop_grace_period", "10s"))
    cmd_in_image = json.loads(next(r for w, r in dockerfile_instructions(DOCKERFILES["cpu"]) if w == "CMD"))
    assert cmd_in_image == cmd, "the CPU image's default command is the API's"


@pytest.mark.parametrize("name,queue_field", [("worker-cpu", "cpu_queue"), ("worker-gpu", "gpu_queue")])
def test_worker_commands(services: dict[str, Any], name: str, queue_field: str) -> None:
    cmd = command(services[name])
    assert cmd[:3] == ["celery", "-A", "worker.celery_app"] and cmd[3] == "worker", cmd
    assert option(cmd, "-c", "--concurrency") == ["1"]
    assert option(cmd, "--prefetch-multiplier") == ["1"]
    # Celery's hard time limits need the prefork pool (the default)
    assert option(cmd, "-P", "--pool") in ([], ["prefork"])
    queue = environment(services[name]).get("CMC_" + queue_field.upper(), Settings.model_fields[queue_field].default)
    assert worker_queues(services[name]) == {queue}


def test_webhook_worker(services: dict[str, Any]) -> None:
    """Webhook tries are short network calls: many at once in threads, on a queue of their own,
    signed with the secret the API derives each key's secret from."""
    svc = services["worker-webhooks"]
    cmd = command(svc)
    assert cmd[:4] == ["celery", "-A", "worker.celery_app", "worker"], cmd
    assert option(cmd, "-P", "--pool") == ["threads"] and int(option(cmd, "-c", "--concurrency")[0]) > 1
    env = environment(svc)
    assert worker_queues(svc) == {env.get("CMC_WEBHOOK_QUEUE", Settings.model_fields["webhook_queue"].default)}
    assert env["CMC_WEBHOOK_SECRET"] == environment(services["api"])["CMC_WEBHOOK_SECRET"]
    for name in ("worker-cpu", "worker-gpu"):
        assert worker_queues(svc).isdisjoint(worker_queues(services[name])), "webhooks would wait behind jobs"
    signed = load_compose(**SECRETS, CMC_WEBHOOK_SECRET="s3cret")["services"]
    assert {environment(signed[n])["CMC_WEBHOOK_SECRET"] for n in APP_SERVICES} == {"s3cret"}


_CELERY_PROBE = """
import json, sys
import worker.celery_app as m
from service.settings import Settings
others = json.loads(sys.argv[1])
print(json.dumps({
    "tasks": sorted(t for t in m.app.tasks if not t.startswith("celery.")),
    "routes": m.app.conf.task_routes,
    "other_routes": {name: m.create_celery(Settings(**fields)).conf.task_routes for name, fields in others.items()},
}))
"""


def _settings_fields(env: dict[str, str]) -> dict[str, str]:
    return {k[4:].lower(): v for k, v in env.items() if k.startswith("CMC_")}


PROBED_WORKERS = ["worker-cpu", "worker-gpu", "worker-webhooks"]


@pytest.fixture(scope="module", autouse=True)
def celery_probe(services: dict[str, Any], tmp_path_factory: pytest.TempPathFactory) -> Iterator[subprocess.Popen[str]]:
    """Import worker.celery_app with the first worker's compose environment, in a child process
    (the module reads its settings at import and registers shared Celery tasks, which must not
    leak into this test process), and build the other workers' apps with the module's own
    create_celery. Started once, before the first test, so that it runs beside the others.
    Broker, database and folders point at nothing that is used: building a Celery app connects
    to nothing."""
    tmp = tmp_path_factory.mktemp("celery-probe")
    unused = dict(broker_url="redis://127.0.0.1:6379/15", database_url=f"sqlite:///{tmp / 'unused.db'}")
    unused.update(data_dir=str(tmp), storage_dir=str(tmp / "storage"))
    child_env = {k: v for k, v in os.environ.items() if not k.startswith("CMC_")}
    child_env.update(environment(services[PROBED_WORKERS[0]]))
    child_env.update({"CMC_" + k.upper(): v for k, v in unused.items()})
    others = {w: {**_settings_fields(environment(services[w])), **unused} for w in PROBED_WORKERS[1:]}
    proc = subprocess.Popen(
        [sys.executable, "-c", _CELERY_PROBE, json.dumps(others)],
        cwd=ROOT,
        env=child_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    yield proc
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


def test_celery_routes_reach_the_workers(services: dict[str, Any], celery_probe: subprocess.Popen[str]) -> None:
    from service.jobs import TASK_NAMES, CeleryJobQueue

    out, err = celery_probe.communicate(timeout=60)
    assert celery_probe.returncode == 0, err
    probe = json.loads(out)
    routes = {PROBED_WORKERS[0]: probe["routes"], **probe["other_routes"]}
    consumer = {"poses": "worker-cpu", "train": "worker-gpu", "video": "worker-gpu", "webhook": "worker-webhooks"}
    assert set(consumer) == set(TASK_NAMES)
    api = Settings(**_settings_fields(environment(services["api"])))
    for phase, task in TASK_NAMES.items():
        assert task in probe["tasks"], f"{task} is not registered by worker.celery_app"
        worker = consumer[phase]
        queue = routes[worker][task]["queue"]
        assert queue in worker_queues(services[worker]), f"{task} is routed to {queue!r}; {worker} consumes others"
        # the API sends tasks by name to the queues its own settings name: the same ones
        assert CeleryJobQueue(api.broker_url, api.cpu_queue, api.gpu_queue, api.webhook_queue).queues[phase] == queue


@pytest.mark.parametrize("name,node", [("worker-cpu", "cpu"), ("worker-gpu", "gpu"), ("worker-webhooks", "webhooks")])
def test_worker_healthcheck_pings_its_own_node(services: dict[str, Any], name: str, node: str) -> None:
    names = option(command(services[name]), "-n", "--hostname")
    assert names == [f"{node}@%h"]
    test = services[name]["healthcheck"]["test"]
    assert test[0] == "CMD-SHELL", "$HOSTNAME needs a shell"
    shell = healthcheck_shell(services[name])
    assert "celery -A worker.celery_app inspect ping" in shell
    # %h is the container's hostname, which the shell has as $HOSTNAME ($$ in the compose file)
    assert option(shlex.split(shell), "-d", "--destination") == [names[0].replace("%h", "$HOSTNAME")]
    assert f"{node}@$$HOSTNAME" in COMPOSE.read_text()


def test_artifacts_in_the_bucket_not_a_shared_volume(compose: dict[str, Any], services: dict[str, Any]) -> None:
    """The API and the workers store artifacts in MinIO's bucket, which minio-init makes before
    they start; none of them mounts a named volume (they may run on different hosts); each has a
    writable /data of its own (an anonymous volume: the root filesystem is read-only)."""
    from service.storage.s3 import S3Storage

    minio = services["minio"]
    minio_env = environment(minio)
    assert command(minio)[:2] == ["server", "/data"] and any(v.endswith(":/data") for v in minio["volumes"])
    named = compose.get("volumes") or {}
    assert any(v.split(":")[0] in named for v in minio["volumes"]), "MinIO's data would be lost with its container"
    init = services["minio-init"]
    assert init["depends_on"]["minio"]["condition"] == "service_healthy"
    init_script = " ".join(command(init))
    storages = set()
    for name in APP_SERVICES:
        env = environment(services[name])
        storages.add((env["CMC_STORAGE"], env["CMC_S3_ENDPOINT_URL"], env["CMC_S3_PUBLIC_ENDPOINT_URL"]))
        assert env["AWS_ACCESS_KEY_ID"] == minio_env["MINIO_ROOT_USER"]
        assert env["AWS_SECRET_ACCESS_KEY"] == minio_env["MINIO_ROOT_PASSWORD"] == SECRETS["MINIO_ROOT_PASSWORD"]
        deps = services[name]["depends_on"]
        assert deps["minio-init"]["condition"] == "service_completed_successfully", f"{name} may start bucketless"
        volumes = services[name]["volumes"]
        mounts = [v if isinstance(v, str) else f"{v.get('source', '')}:{v['target']}" for v in volumes]
        assert not [m for m in mounts if m.split(":")[0] in named], f"{name} mounts a named volume: {mounts}"
        assert env["CMC_DATA_DIR"] in mounts, f"{name}: {env['CMC_DATA_DIR']} is not writable"
    assert len(storages) == 1, f"the services disagree on the storage: {storages}"
    storage, endpoint, public = storages.pop()
    url = urlsplit(endpoint)
    assert (url.hostname, url.port) == ("minio", 9000)
    s3 = S3Storage.from_settings(Settings(storage=storage, s3_endpoint_url=endpoint))
    assert f"mc mb --ignore-existing cmc/{s3.bucket}" in init_script
    assert f"mc alias set cmc {endpoint} {minio_env['MINIO_ROOT_USER']}" in init_script
    # presigned URLs point at MinIO's published port
    published = [p.rsplit(":", 2) for p in minio["ports"]]
    assert [(int(host_port), int(port)) for _, host_port, port in published] == [(urlsplit(public).port, 9000)]
    # a new volume takes the owner of the image's folder: the images must make /data theirs
    # (both run docker/install-service.sh: test_image_runs_under_a_read_only_root)
    script = INSTALL_SCRIPT.read_text()
    assert re.search(r"mkdir -p /data\b", script), f"{INSTALL_SCRIPT.name} does not create /data"
    assert re.search(r"chown \S+ /data\b", script), f"{INSTALL_SCRIPT.name} does not chown /data"


def test_api_and_workers_share_database_and_broker(services: dict[str, Any]) -> None:
    from sqlalchemy.engine import make_url

    db_urls = {environment(services[n])["CMC_DATABASE_URL"] for n in APP_SERVICES}
    broker_urls = {environment(services[n])["CMC_BROKER_URL"] for n in APP_SERVICES}
    assert len(db_urls) == 1 and len(broker_urls) == 1
    url = make_url(db_urls.pop())
    pg = environment(services["db"])
    assert url.drivername == "postgresql+psycopg"
    assert (url.host, url.port or 5432) == ("db", 5432)
    assert url.username == pg["POSTGRES_USER"] and url.database == pg["POSTGRES_DB"]
    assert url.password == pg["POSTGRES_PASSWORD"] == SECRETS["POSTGRES_PASSWORD"]
    broker = urlsplit(broker_urls.pop())
    assert broker.scheme == "redis" and broker.hostname == "redis" and (broker.port or 6379) == 6379


def test_database_and_redis(services: dict[str, Any], compose: dict[str, Any]) -> None:
    assert re.fullmatch(r"postgres:16(\.\d+)*(-\w+)?", services["db"]["image"])
    assert re.fullmatch(r"redis:7(\.\d+)*(-\w+)?", services["redis"]["image"])
    redis_cmd = command(services["redis"])
    assert option(redis_cmd, "--appendonly") == ["yes"], "queued jobs would not survive a Redis restart"
    named = compose.get("volumes") or {}
    for name, path in (("db", "/var/lib/postgresql/data"), ("redis", "/data")):
        vols = [v.split(":") for v in services[name]["volumes"]]
        assert any(src in named and dst == path for src, dst, *_ in vols), f"{name}: no named volume at {path}"


def test_healthchecks_and_dependencies(services: dict[str, Any]) -> None:
    for name in ("redis", "db", "minio", *APP_SERVICES):
        hc = services[name].get("healthcheck")
        assert hc and not hc.get("disable") and hc["test"] not in (["NONE"], "NONE"), f"{name}: no health check"
    assert "pg_isready" in healthcheck_shell(services["db"])
    assert "redis-cli ping" in healthcheck_shell(services["redis"])
    assert "/readyz" in healthcheck_shell(services["api"])
    for name in APP_SERVICES:
        deps = services[name]["depends_on"]
        assert isinstance(deps, dict), f"{name}: depends_on without conditions"
        for dep in ("db", "redis"):
            assert deps[dep]["condition"] == "service_healthy", f"{name} does not wait for {dep}"
        # the one-shot steps, run to completion first: the schema migration and the bucket
        assert deps["migrate"]["condition"] == "service_completed_successfully", f"{name} may see an old schema"
        assert deps["minio-init"]["condition"] == "service_completed_successfully", f"{name} may start bucketless"
        one_shots = ("migrate", "minio-init")
        assert all(d["condition"] == "service_healthy" for dep, d in deps.items() if dep not in one_shots)


def test_migrations_run_once_before_the_api_and_workers(services: dict[str, Any]) -> None:
    """The deployed mode migrates the schema in a one-shot step (python -m service.db.migrate) that
    waits for the database; the API and the workers do not migrate on start themselves."""
    migrate = services["migrate"]
    assert command(migrate) == ["python", "-m", "service.db.migrate"]
    assert migrate["image"] == services["api"]["image"] and str(migrate.get("restart", "no")) == "no"
    assert migrate["depends_on"]["db"]["condition"] == "service_healthy"
    assert environment(migrate)["CMC_DATABASE_URL"] == environment(services["api"])["CMC_DATABASE_URL"]
    for name in APP_SERVICES:
        assert environment(services[name])["CMC_MIGRATE_ON_START"] == "false", name


def test_gpu_worker(services: dict[str, Any]) -> None:
    gpu = services["worker-gpu"]
    devices = gpu["deploy"]["resources"]["reservations"]["devices"]
    assert any(
        d.get("driver") == "nvidia" and "gpu" in d.get("capabilities", []) and (d.get("count") or d.get("device_ids"))
        for d in devices
    ), devices
    assert PurePosixPath(gpu["build"]["dockerfile"]) == PurePosixPath("docker/Dockerfile.gpu")
    assert environment(gpu)["CMC_DEVICE"].startswith("cuda")
    # the build arguments compose passes exist in the Dockerfile, with the same defaults
    args = dockerfile_args(DOCKERFILES["gpu"])
    defaults = load_compose(**SECRETS, GPU_CUDA_IMAGE="", GPU_TORCH_INDEX_URL="")["services"]["worker-gpu"]
    for key in gpu["build"].get("args", {}):
        assert key in args, f"Dockerfile.gpu has no ARG {key}"
        assert defaults["build"]["args"][key] == args[key], f"{key}: compose and Dockerfile.gpu defaults differ"
    # the wheel index and the base image name the same CUDA major.minor (cu130 <-> 13.0.x), in
    # the Dockerfile's defaults and in .env.example
    example = read_env_file(ENV_EXAMPLE)
    for cuda, index in (
        (args["CUDA_IMAGE"], args["TORCH_INDEX_URL"]),
        (example["GPU_CUDA_IMAGE"], example["GPU_TORCH_INDEX_URL"]),
    ):
        m = re.search(r"/whl/cu(\d+)(\d)$", index)
        assert m and re.match(rf"nvidia/cuda:{m[1]}\.{m[2]}\.\d+-\w+", cuda), (cuda, index)


def test_cpu_services_use_the_cpu_image(services: dict[str, Any]) -> None:
    for name in ("api", "worker-cpu", "worker-webhooks"):
        assert PurePosixPath(services[name]["build"]["dockerfile"]) == PurePosixPath("docker/Dockerfile")
    assert services["api"]["image"] == services["worker-cpu"]["image"] != services["worker-gpu"]["image"]
    assert services["worker-webhooks"]["image"] == services["api"]["image"]


# -- the images --------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", sorted(DOCKERFILES))
def test_dockerfile(kind: str) -> None:
    path = DOCKERFILES[kind]
    ins = dockerfile_instructions(path)
    ignored = [p for p in (ROOT / ".dockerignore").read_text().splitlines() if p and not p.startswith(("#", "!"))]
    copied = set()
    for word, rest in ins:
        if word in ("COPY", "ADD"):
            parts = [p for p in shlex.split(rest) if not p.startswith("--")]
            if any(p.startswith("--from") for p in shlex.split(rest)):
                continue
            for src in parts[:-1]:
                name = src.rstrip("/")
                assert (ROOT / name).exists(), f"{path.name}: COPY {src}: not in the repository"
                assert not any(fnmatch.fnmatch(name, pat.rstrip("/")) for pat in ignored), f".dockerignore drops {src}"
                copied.add(name)
    assert {"pyproject.toml", "cmc", "service", "worker"} <= copied
    assert ("WORKDIR", "/src") in ins
    users = [rest for word, rest in ins if word == "USER"]
    assert users and users[-1] not in ("root", "0"), "runs as root"
    # torch first, from the wheel index, pinned like pyproject.toml; then the other dependencies
    runs = [(i, rest) for i, (word, rest) in enumerate(ins) if word == "RUN"]
    torch_runs = [i for i, r in runs if re.search(r"pip install\b.*\btorch==", r)]
    assert torch_runs, f"{path.name}: torch is not installed on its own"
    for i in torch_runs:
        assert re.search(r"torch==[\w.+]+", ins[i][1])[0] == torch_pin()
        assert "--index-url" in ins[i][1]
    deps_run = next(i for i, r in runs if "tomllib" in r)
    source_copy = next(i for i, (word, rest) in enumerate(ins) if word == "COPY" and rest.startswith("cmc"))
    assert max(torch_runs) < deps_run < source_copy, "dependencies must install before the code is copied"
    # and nothing but pyproject.toml is copied before them, or any edit reinstalls everything
    early = [rest for word, rest in ins[:deps_run] if word in ("COPY", "ADD") and "--from" not in rest]
    assert [shlex.split(rest)[:-1] for rest in early] == [["pyproject.toml"]], early


def test_dockerfiles_share_uid_and_python() -> None:
    script = INSTALL_SCRIPT.read_text()
    m = re.search(r"useradd\b[^\n]*--uid (\d+)", script)
    assert m, f"{INSTALL_SCRIPT.name}: no useradd --uid"
    for path in DOCKERFILES.values():
        user = [rest for word, rest in dockerfile_instructions(path) if word == "USER"][-1]
        assert user.split(":")[0] == m[1], f"{path.name}: USER {user} is not the uid the script creates ({m[1]})"
    want = re.search(r">=\s*(3\.\d+)", pyproject()["requires-python"])[1]
    froms = [rest for word, rest in dockerfile_instructions(DOCKERFILES["cpu"]) if word == "FROM"]
    assert froms[-1].startswith(f"python:{want}-")
    assert f"uv python install {want}" in DOCKERFILES["gpu"].read_text()


@pytest.mark.parametrize("kind", sorted(DOCKERFILES))
def test_image_runs_under_a_read_only_root(kind: str, services: dict[str, Any]) -> None:
    """What the service user may write at run time under compose's read_only root (the tmpfs /tmp
    and the volume /data) is where the image points every cache: numba's kernels (seeded at build
    time by docker/install-service.sh, tests/test_kernel_cache.py), $HOME, the working folder."""
    ins = dockerfile_instructions(DOCKERFILES[kind])
    env: dict[str, str] = {}
    for word, rest in ins:
        if word == "ENV":
            env.update(dict(kv.split("=", 1) for kv in shlex.split(rest)))
    writable = [PurePosixPath(p) for p in services["api"]["tmpfs"]] + [PurePosixPath("/data")]
    for var in ("NUMBA_CACHE_DIR", "HOME"):
        assert any(PurePosixPath(env[var]).is_relative_to(w) for w in writable), f"{var}={env[var]}"
    assert not any(PurePosixPath(env["CMC_KERNEL_CACHE_SEED"]).is_relative_to(w) for w in writable)
    run = [rest for word, rest in ins if word == "RUN"][-1]
    assert run == "sh docker/install-service.sh", "the last build step is the shared install script"
    workdirs = [rest for word, rest in ins if word == "WORKDIR"]
    assert PurePosixPath(workdirs[-1]) in writable, "the processes start in a writable folder"
    # one copy of the code: the script installs it, then deletes the folder it was copied to
    script = INSTALL_SCRIPT.read_text()
    assert 'pip install --no-deps "$src"' in script and 'rm -rf "$src"' in script
    assert PurePosixPath(workdirs[-2]) != PurePosixPath(workdirs[-1])


@pytest.mark.parametrize("kind", sorted(DOCKERFILES))
def test_dependency_layer_installs_pyproject(kind: str) -> None:
    """Run the Dockerfile's own requirements-extraction command on this pyproject.toml."""
    path = DOCKERFILES[kind]
    run = next(rest for word, rest in dockerfile_instructions(path) if word == "RUN" and "tomllib" in rest)
    script = run.split(">", 1)[0].strip()
    assert script.startswith("python -c ")
    script = shlex.quote(sys.executable) + script[len("python") :]
    extras = dockerfile_args(path)["EXTRAS"]
    out = subprocess.run(
        ["sh", "-c", script],
        cwd=ROOT,
        env={**os.environ, "EXTRAS": extras},
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    ).stdout.split()
    project = pyproject()
    want = project["dependencies"] + [d for e in extras.split() for d in project["optional-dependencies"][e]]
    assert out == [d.replace(" ", "") for d in want]
    assert torch_pin() in out


def test_dockerignore_keeps_secrets_and_clutter_out() -> None:
    patterns = {p.strip().rstrip("/") for p in (ROOT / ".dockerignore").read_text().splitlines()}
    assert {".env", ".venv", ".git", "tests"} <= patterns


# -- docker compose itself, where the plugin is installed --------------------------------------


def _compose_plugin() -> bool:
    if not shutil.which("docker"):
        return False
    r = subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=20)
    return r.returncode == 0


def test_docker_compose_config_validates() -> None:
    if not _compose_plugin():
        pytest.skip("the docker compose plugin is not installed here")
    base = [k for k in os.environ if k not in SECRETS and k not in read_env_file(ENV_EXAMPLE)]
    env = {k: os.environ[k] for k in base}
    args = ["docker", "compose", "-f", str(COMPOSE), "--env-file", str(ENV_EXAMPLE), "config", "-q"]
    ok = subprocess.run(args, cwd=ROOT, env={**env, **SECRETS}, capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr
    no_keys = {**env, "POSTGRES_PASSWORD": SECRETS["POSTGRES_PASSWORD"]}
    refused = subprocess.run(args, cwd=ROOT, env=no_keys, capture_output=True, text=True, timeout=60)
    assert refused.returncode != 0 and "CMC_API_KEYS" in refused.stderr + refused.stdout


# -- the CPU-only deployment (docker-compose.cpu.yml) -------------------------------------------


class _Reset:
    """Compose's ``!reset`` tag: the key is removed from the merged file."""


class _Override:
    """Compose's ``!override`` tag: the value replaces the base file's instead of merging."""

    def __init__(self, value: Any) -> None:
        self.value = value


class _ComposeLoader(yaml.SafeLoader):
    pass


_ComposeLoader.add_constructor("!reset", lambda loader, node: _Reset())
_ComposeLoader.add_constructor("!override", lambda loader, node: _Override(loader.construct_mapping(node, deep=True)))


def merge_compose(base: Any, override: Any) -> Any:
    """Compose's merge of an override file into ``base``: mappings merge key by key, ``!reset``
    removes, ``!override`` replaces, other values replace (enough for the files here)."""
    if isinstance(override, _Override):
        return override.value
    if isinstance(base, dict) and isinstance(override, dict):
        out = dict(base)
        for k, v in override.items():
            if isinstance(v, _Reset):
                out.pop(k, None)
            else:
                out[k] = merge_compose(base.get(k), v)
        return out
    return override


def test_cpu_only_deployment_trains_on_the_cpu_image(services: dict[str, Any]) -> None:
    """docker-compose.cpu.yml: the training worker without a GPU reservation, on the CPU image
    (built by the CPU Dockerfile with no CUDA build arguments), training on the CPU."""
    override = yaml.load((ROOT / "docker-compose.cpu.yml").read_text(), Loader=_ComposeLoader)  # noqa: S506
    assert set(override["services"]) == {"worker-gpu"}
    merged = merge_compose(services, override["services"])
    worker = merged["worker-gpu"]
    assert "deploy" not in worker, "a CPU host has no device to reserve"
    assert worker["build"] == services["api"]["build"] and "args" not in worker["build"]
    assert worker["image"] == services["api"]["image"]
    assert worker["environment"]["CMC_DEVICE"] == "cpu"
    assert command(worker) == command(services["worker-gpu"]), "it still consumes the training queue"
