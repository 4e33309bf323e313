"""API keys: ``Authorization: Bearer <key>``, compared by SHA-256 digest (keys are never stored).

Keys come from ``CMC_API_KEYS`` (comma-separated; hashed when loaded) and ``CMC_API_KEYS_FILE``
(one SHA-256 hex digest a line, ``#`` comments; ``cmc serve --new-key FILE`` appends one). With
no key configured the API is open: ``cmc serve`` then only listens on localhost, and
:class:`service.middleware.LocalOnly` answers only local host names and same-site pages. A scene
belongs to the key that made it: its owner id is the key digest's first 16 hex digits (``local``
in open mode), and other keys get 404 for it.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
from pathlib import Path

from service.errors import APIError, ErrorCode

OPEN_OWNER = "local"
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


def key_digest(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def new_key() -> tuple[str, str]:
    """A fresh random key and its digest (to put in the keys file)."""
    key = "cmc_" + secrets.token_urlsafe(32)
    return key, key_digest(key)


class KeyRing:
    def __init__(self, digests: set[str]):
        self.digests = frozenset(digests)

    @staticmethod
    def load(keys: str, keys_file: Path | None) -> KeyRing:
        digests = {key_digest(k.strip()) for k in keys.split(",") if k.strip()}
        if keys_file is not None:
            for n, line in enumerate(Path(keys_file).read_text().splitlines(), 1):
                line = line.split("#", 1)[0].strip().lower()
                if not line:
                    continue
                if not _HEX64.match(line):
                    raise ValueError(f"{keys_file}:{n}: expected a SHA-256 hex digest of a key")
                digests.add(line)
        return KeyRing(digests)

    @property
    def open(self) -> bool:
        """No keys configured: every request is accepted (localhost only)."""
        return not self.digests

    def owner(self, authorization: str | None) -> str:
        """The owner id of the request's key; raises 401 when keys are configured and it is
        missing or unknown."""
        if self.open:
            return OPEN_OWNER
        scheme, _, token = (authorization or "").partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            hint = "send an API key: Authorization: Bearer <key>"
            raise APIError(401, ErrorCode.unauthorized, hint, headers={"WWW-Authenticate": "Bearer"})
        digest = key_digest(token.strip())
        if not any(hmac.compare_digest(digest, d) for d in self.digests):
            raise APIError(401, ErrorCode.unauthorized, "unknown API key", headers={"WWW-Authenticate": "Bearer"})
        return digest[:16]
