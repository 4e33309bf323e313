"""``cmc serve``: the API with the embedded job runner (no Redis, no GPU needed), and
``cmc new-api-key``. Registered into the ``cmc`` command by cmc/cli.py."""

from __future__ import annotations

import argparse
import ipaddress
import os
import socket
from pathlib import Path
from typing import Any

from cmc.errors import ConfigError


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(socket.gethostbyname(host)).is_loopback
    except (OSError, ValueError):
        return False


def cmd_serve(args: argparse.Namespace) -> None:
    import uvicorn

    from service.app import create_app
    from service.auth import KeyRing
    from service.settings import load_settings
    from worker.embedded import EmbeddedRunner

    settings = load_settings(data_dir=Path(args.data_dir), mode="embedded")
    keys = KeyRing.load(settings.api_keys, settings.api_keys_file)
    if keys.open and not _is_loopback(args.host):
        raise ConfigError(
            f"refusing to listen on {args.host} without API keys: set CMC_API_KEYS or CMC_API_KEYS_FILE "
            "(see cmc new-api-key), or listen on 127.0.0.1"
        )
    url = f"http://{args.host}:{args.port}"
    print(f"CMC API on {url} (docs {url}/docs), data in {settings.data_dir.resolve()}, jobs run in this process")
    if keys.open:
        print("No API keys configured: accepting requests without a key, on this machine only.")
    else:
        print(f"API key required ({len(keys.digests)} configured).")
    app = create_app(settings, embedded_runner=EmbeddedRunner)  # the one place the API meets worker/
    # on a stop, requests still running after 15 s (a slow upload) are cancelled, removing what they staged
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level, timeout_graceful_shutdown=15)


def cmd_new_api_key(args: argparse.Namespace) -> None:
    from service.auth import new_key

    key, digest = new_key()
    path = Path(args.file)
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
    with os.fdopen(fd, "a") as f:
        f.write(f"{digest}  # {args.label}\n" if args.label else f"{digest}\n")
    print(key)
    print(f"(its SHA-256 digest was appended to {path}; the key itself is not stored: keep it now)")


def register_cli(subparsers: Any) -> None:
    s = subparsers.add_parser("serve", help="run the REST API with an in-process job runner (no Redis, no GPU)")
    s.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    s.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    s.add_argument(
        "--data-dir", default=os.environ.get("CMC_DATA_DIR", "cmc-data"), help="database and artifacts (./cmc-data)"
    )
    s.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    s.set_defaults(func=cmd_serve)
    k = subparsers.add_parser("new-api-key", help="make an API key and append its digest to a keys file")
    k.add_argument("file", help="keys file (CMC_API_KEYS_FILE), created if missing")
    k.add_argument("--label", help="comment stored beside the digest (e.g. the app's name)")
    k.set_defaults(func=cmd_new_api_key)
