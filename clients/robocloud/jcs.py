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


def canonical(value: Any, *, exact_integers: bool = False) -> bytes:
    """The RFC 8785 bytes of ``value`` (dicts with string keys, lists, str, int, float, ...).

    RFC 8785 leaves integers beyond +-(2**53 - 1) out of its domain (an ECMAScript reader would
    round them), and refuses them here. ``exact_integers`` writes them with all their digits
    instead, as any JSON parser with exact integers reads them back: a record's time in
    nanoseconds since the epoch (about 1.7e18) is such an integer, and rounding it would let
    two records share one leaf. Every value inside RFC 8785's domain gets the same bytes
    either way.
    """
    try:
        if exact_integers:
            out: list[bytes] = []
            _dump_exact(value, out, 0)
            return b"".join(out)
        return rfc8785.dumps(value)
    except rfc8785.CanonicalizationError as exc:
        raise JcsError(f"not canonicalizable: {exc}") from exc
    except (TypeError, RecursionError) as exc:
        raise JcsError(f"not a JSON value: {exc}") from exc


def _dump_exact(value: Any, out: list[bytes], depth: int) -> None:
    """RFC 8785 with exact integers; its nesting bounded like every JSON document's."""
    if depth > bounded_json.MAX_DEPTH:
        raise JcsError(f"nested deeper than {bounded_json.MAX_DEPTH} levels")
    if isinstance(value, int) and not isinstance(value, bool):
        out.append(str(int(value)).encode())
    elif isinstance(value, dict):
        if not all(isinstance(key, str) for key in value):
            raise JcsError("not a JSON value: an object key is not a string")
        out.append(b"{")
        for position, key in enumerate(sorted(value, key=lambda name: name.encode("utf-16-be"))):
            if position:
                out.append(b",")
            out.append(rfc8785.dumps(key))
            out.append(b":")
            _dump_exact(value[key], out, depth + 1)
        out.append(b"}")
    elif isinstance(value, list | tuple):
        out.append(b"[")
        for position, item in enumerate(value):
            if position:
                out.append(b",")
            _dump_exact(item, out, depth + 1)
        out.append(b"]")
    else:
        out.append(rfc8785.dumps(value))


def canonicalize(document: bytes | str, *, max_depth: int = bounded_json.MAX_DEPTH) -> bytes:
    """Parse a JSON document (nesting bounded) and return its canonical bytes."""
    return canonical(bounded_json.loads(document, max_depth=max_depth))
