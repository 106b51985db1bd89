"""JSON Canonicalization Scheme (RFC 8785): the one byte form of a JSON value.

A record's identity and its Merkle leaf are hashes of these bytes, so a robot and a storage
node must produce them identically from the same value: keys sorted by UTF-16 code units,
numbers in ECMAScript's shortest form, no insignificant whitespace. ``rfc8785`` implements
the scheme; this module bounds what it is given and names what cannot be canonical.
"""

from __future__ import annotations

from typing import Any

import rfc8785

from robocloud import bounded_json
from robocloud.errors import FormatError

MAX_SAFE_INTEGER = 2**53 - 1
"""I-JSON (RFC 7493) integers: beyond this an ECMAScript reader would round them."""


class JcsError(FormatError):
    """A value JSON canonicalization cannot represent: NaN, infinities, unsafe integers."""


def canonical(value: Any) -> bytes:
    """The RFC 8785 bytes of ``value`` (dicts with string keys, lists, str, int, float, ...)."""
    try:
        return rfc8785.dumps(value)
    except rfc8785.CanonicalizationError as exc:
        raise JcsError(f"not canonicalizable: {exc}") from exc
    except (TypeError, RecursionError) as exc:
        raise JcsError(f"not a JSON value: {exc}") from exc


def canonicalize(document: bytes | str, *, max_depth: int = bounded_json.MAX_DEPTH) -> bytes:
    """Parse a JSON document (nesting bounded) and return its canonical bytes."""
    return canonical(bounded_json.loads(document, max_depth=max_depth))
