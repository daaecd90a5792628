"""Digests of JSON-able values: how the stage cache and the capture reader key what a stage depends on."""

from __future__ import annotations

import hashlib
import json
from typing import Any

#: Hex digits kept of a SHA-256: 128 bits, far beyond any chance collision among a run's keys.
DIGEST_HEX = 32


def canonical_json(value: Any) -> str:
    """``value`` as JSON with sorted keys and no spaces, so that equal values give equal text (NaN refused)."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)


def bytes_digest(data: bytes) -> str:
    """The first ``DIGEST_HEX`` hex digits of the SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()[:DIGEST_HEX]


def text_digest(text: str) -> str:
    """:func:`bytes_digest` of ``text`` (UTF-8)."""
    return bytes_digest(text.encode("utf-8"))
