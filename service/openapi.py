"""Write the API's OpenAPI spec to ``openapi/openapi.json``: ``python -m service.openapi``.

The committed file is what clients generate code from; tests/test_openapi.py fails when it
differs from what the app serves at ``/openapi.json``, so regenerate it whenever the API moves.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

SPEC_PATH = Path(__file__).resolve().parent.parent / "openapi" / "openapi.json"


def current_spec() -> dict:
    """The spec of an app built with default settings (in a throw-away data folder)."""
    from service.app import create_app
    from service.settings import load_settings

    with tempfile.TemporaryDirectory() as tmp:
        app = create_app(load_settings(data_dir=Path(tmp), api_keys="", api_keys_file=None, mode="embedded"))
        spec = app.openapi()
        app.state.services.store.close()
        return spec


def render(spec: dict) -> str:
    return json.dumps(spec, indent=2, sort_keys=True) + "\n"


def main() -> int:
    SPEC_PATH.parent.mkdir(exist_ok=True)
    SPEC_PATH.write_text(render(current_spec()))
    print(f"wrote {SPEC_PATH}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
