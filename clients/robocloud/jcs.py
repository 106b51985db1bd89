"""JSON Canonicalization Scheme (RFC 8785): the one byte form of a JSON value.

A record's identity and its Merkle leaf are hashes of these bytes, so a robot and a storage
node must produce them identically from the same value: keys sorted by UTF-16 code units,
numbers in ECMAScript's shortest form, strings with only the escapes JSON requires, no
insignificant whitespace.

Written here rather than through the ``rfc8785`` package because ingestion canonicalizes every
record: that package formats each float digit by digit in Python (about 2 us a float, most of a
ROS IMU record's cost), while ``repr`` already yields the shortest round-tripping digits that
ECMAScript prints and only their layout differs. The tests hold this module to ``rfc8785`` and
to the RFC's own examples on the same values.
"""

from __future__ import annotations

import math
from json.encoder import encode_basestring
from typing import Any

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
    out: list[str] = []
    _dump(value, out, 0, exact_integers)
    try:
        return "".join(out).encode()
    except UnicodeEncodeError as exc:
        raise JcsError("not canonicalizable: a string holds a lone surrogate") from exc


def canonicalize(document: bytes | str, *, max_depth: int = bounded_json.MAX_DEPTH) -> bytes:
    """Parse a JSON document (nesting bounded) and return its canonical bytes."""
    return canonical(bounded_json.loads(document, max_depth=max_depth))


def _dump(value: Any, out: list[str], depth: int, exact_integers: bool) -> None:
    """One value; containers recurse, at most as deep as any JSON document may nest."""
    kind = type(value)
    if kind is float:
        out.append(_number(value))
    elif kind is str:
        out.append(_string(value))
    elif kind is int:
        if not exact_integers and not -MAX_SAFE_INTEGER <= value <= MAX_SAFE_INTEGER:
            raise JcsError(f"not canonicalizable: {value} is beyond +-(2**53 - 1)")
        out.append(str(value))
    elif kind is dict or kind is list or kind is tuple:
        if depth >= bounded_json.MAX_DEPTH:
            raise JcsError(f"nested deeper than {bounded_json.MAX_DEPTH} levels")
        if kind is dict:
            _dump_object(value, out, depth + 1, exact_integers)
        else:
            out.append("[")
            for position, item in enumerate(value):
                if position:
                    out.append(",")
                _dump(item, out, depth + 1, exact_integers)
            out.append("]")
    elif value is None:
        out.append("null")
    elif value is True:
        out.append("true")
    elif value is False:
        out.append("false")
    elif isinstance(value, str | int | float | dict | list):
        _dump(_plain(value), out, depth, exact_integers)
    else:
        raise JcsError(f"not a JSON value: {type(value).__name__}")


def _dump_object(value: dict[Any, Any], out: list[str], depth: int, exact_integers: bool) -> None:
    if not all(type(key) is str for key in value):
        raise JcsError("not a JSON value: an object key is not a string")
    out.append("{")
    keys = sorted(value) if all(key.isascii() for key in value) else sorted(value, key=_utf16)
    for position, key in enumerate(keys):
        if position:
            out.append(",")
        out.append(_string(key))
        out.append(":")
        _dump(value[key], out, depth, exact_integers)
    out.append("}")


def _plain(value: Any) -> Any:
    """A subclass of a JSON type (an enum, an OrderedDict) as its plain base value."""
    bases: tuple[type[Any], ...] = (str, int, float, dict, list)
    return next(base(value) for base in bases if isinstance(value, base))


def _utf16(key: str) -> bytes:
    """RFC 8785 sorts keys by UTF-16 code units, which differs from code points above U+FFFF
    (ASCII keys, the usual case, sort the same either way and skip this)."""
    return key.encode("utf-16-be", "surrogatepass")


def _string(text: str) -> str:
    """A string's canonical JSON: the standard library's encoder (C) escapes exactly what RFC
    8785 does: quote, backslash, ``\\b \\f \\n \\r \\t`` in short form, other controls as
    lowercase ``\\u00xx``, nothing else."""
    return encode_basestring(text)


def _number(value: float) -> str:
    """ECMAScript's Number::toString (RFC 8785 section 3.2.2.3) from Python's shortest repr."""
    if math.isnan(value) or math.isinf(value):
        raise JcsError(f"not canonicalizable: {value} is not a JSON number")
    if value == 0:
        return "0"
    text = repr(abs(value))
    sign = "-" if value < 0 else ""
    if "e" not in text:
        # repr is positional from 1e-4 to 1e16, where ECMAScript is positional too.
        return sign + (text[:-2] if text.endswith(".0") else text)
    mantissa, exponent = text.split("e")
    digits = mantissa.replace(".", "").rstrip("0")
    point = int(exponent) + 1
    """The value is 0.<digits> x 10**point, ECMAScript's k digits and n."""
    if len(digits) <= point <= 21:
        return sign + digits + "0" * (point - len(digits))
    if 0 < point <= 21:
        return sign + digits[:point] + "." + digits[point:]
    if -6 < point <= 0:
        return sign + "0." + "0" * -point + digits
    shown = digits[0] + ("." + digits[1:] if len(digits) > 1 else "")
    return f"{sign}{shown}e{'+' if point > 0 else '-'}{abs(point - 1)}"
