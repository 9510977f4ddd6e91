"""Who is calling: API keys, held as SHA-256 digests and compared in constant time, and the
caller's id that the logs, the rate limits and the fair share of the queues use.

A key is any string of at least MIN_KEY_LENGTH characters (`python -c "import secrets;
print(secrets.token_urlsafe(32))"` makes a good one). It is sent as `Authorization: Bearer KEY`
or `X-API-Key: KEY`, never in the URL (URLs end up in logs and browser histories).
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Iterable, Mapping
from pathlib import Path

MIN_KEY_LENGTH = 16


class InvalidKeys(ValueError):
    """The configured keys cannot be used (a key too short, an empty file)."""


def _digest(key: str) -> bytes:
    return hashlib.sha256(key.encode()).digest()


def key_id(key: str) -> str:
    """A key's short public id (for logs and metrics): the first 8 hex digits of its digest."""
    return _digest(key).hex()[:8]


def read_keys(setting: str) -> list[str]:
    """The keys of the `api_keys` setting: a path to a file of one key per line (blank lines and
    `#` comments skipped), else comma-separated keys. Raises InvalidKeys on a key that is too
    short or on no key at all."""
    path = Path(setting)
    if path.is_file():
        lines = (line.split("#", 1)[0] for line in path.read_text().splitlines())
        keys = [line.strip() for line in lines if line.strip()]
    else:
        keys = [part.strip() for part in setting.split(",") if part.strip()]
    if not keys:
        raise InvalidKeys("api_keys holds no key")
    short = [key_id(k) for k in keys if len(k) < MIN_KEY_LENGTH]
    if short:
        raise InvalidKeys(f"keys shorter than {MIN_KEY_LENGTH} characters (ids {', '.join(short)})")
    return keys


class ApiKeys:
    """The accepted keys, as digests only."""

    def __init__(self, keys: Iterable[str]):
        self._digests = [_digest(k) for k in keys]

    def __len__(self) -> int:
        return len(self._digests)

    def check(self, presented: str) -> str | None:
        """The key's id when `presented` is one of the keys, else None. Every stored digest is
        compared (hmac.compare_digest, no early exit), so the time says nothing of which key
        or how much of it matched."""
        digest = _digest(presented)
        found = False
        for stored in self._digests:
            found |= hmac.compare_digest(digest, stored)
        return digest.hex()[:8] if found else None


def presented_key(headers: Mapping[str, str]) -> str | None:
    """The key a request carries in `Authorization: Bearer KEY` or `X-API-Key`, or None."""
    auth = headers.get("authorization", "")
    scheme, _, value = auth.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    return headers.get("x-api-key") or None
