"""JSON parsing with a bound on nesting, for every document a stranger controls.

CPython's JSON decoder recurses once per nesting level in C. A 200 KB document of 100,000
nested brackets overflows the C stack (a segfault, not an exception) wherever the recursion
limit was raised, and py-evm and py_ecc raise it at import. So the depth is measured first,
with a few passes of C-speed string operations and no recursion, and only a document within
the bound reaches ``json.loads``.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from typing import Any

from robocloud.errors import FormatError

MAX_DEPTH = 64
"""Nesting that robocloud's own documents never come near; services may choose their own."""
MAX_INTEGER_DIGITS = 1000
"""Longer integers are refused: converting them costs quadratic time, and CPython refuses
more than 4,300 digits with a bare ValueError anyway."""

SURROGATE_ESCAPE = re.compile(rb"\\u[dD][89a-fA-F]")
"""The escape a lone surrogate can come from: UTF-8 text cannot hold one otherwise."""
LONE_SURROGATE = re.compile("[\ud800-\udfff]")
"""Half of a UTF-16 surrogate pair in a string: no UTF-8 can carry it (RFC 7493 forbids it)."""
_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)
_NOT_BRACKET = re.compile(rb"[^\[\]{}]+")
_ONE_KIND = bytes.maketrans(b"{}", b"[]")


class JsonError(FormatError):
    """A document that is not JSON, or not JSON within the bounds the reader accepts."""


class JsonNumberError(JsonError):
    """A number JSON does not have (``NaN``, ``Infinity``, or one like ``1e999`` that only a
    float's overflow to infinity could hold) or an integer beyond the bound.

    The document is otherwise well formed, which lets a protocol tell it from a syntax error
    (JSON-RPC answers -32600 rather than -32700).
    """


class JsonSurrogateError(JsonError):
    """A string holding half of a UTF-16 surrogate pair (``"\\ud800"`` alone).

    JSON's grammar lets the escape through, but no UTF-8 text can hold it (I-JSON, RFC 7493,
    forbids it): every later step that encodes the string, a response, a log line, a
    signature's canonical form, would fail on it after the document was accepted.
    """


class JsonDuplicateKeyError(JsonError):
    """An object naming one key twice. JSON's grammar lets it through and ``json`` keeps the
    last value, but I-JSON (RFC 7493) forbids it: another reader keeping the first would read
    another document under the same signature, and JCS (RFC 8785), which hashes records for
    their Merkle proofs, is defined on I-JSON only."""

    def __init__(self, key: str) -> None:
        super().__init__(f"the key {key[:80]!r} appears twice in one object")
        self.key = key


class JsonDepthError(JsonError):
    """A document nested deeper than the reader's bound; ``max_depth`` is that bound."""

    def __init__(self, max_depth: int) -> None:
        super().__init__(f"JSON nested deeper than {max_depth} levels")
        self.max_depth = max_depth


def exceeds_depth(document: bytes, max_depth: int) -> bool:
    """Whether parsing ``document`` could nest deeper than ``max_depth``.

    Brackets outside strings are reduced to ``[`` and ``]``; each pass then removes every
    adjacent ``[]`` pair, one nesting level, so balanced nesting of depth d takes d passes.
    What no pass removes has the form ``]...][...[``: a parser stops at the first unmatched
    ``]``, and otherwise descends into every unclosed ``[``, so those count too.
    """
    if document.count(b"[") + document.count(b"{") <= max_depth:
        return False
    brackets = _NOT_BRACKET.sub(b"", _STRING.sub(b"", document)).translate(_ONE_KIND)
    passes = 0
    while (reduced := brackets.replace(b"[]", b"")) != brackets:
        passes += 1
        if passes > max_depth:
            return True
        brackets = reduced
    unclosed = 0 if brackets.startswith(b"]") else len(brackets)
    return passes + unclosed > max_depth


def loads(
    document: bytes | str,
    *,
    max_depth: int = MAX_DEPTH,
    object_pairs_hook: Callable[[list[tuple[str, Any]]], Any] | None = None,
) -> Any:
    """Parse ``document``; raise :class:`JsonDepthError` or :class:`JsonError` when it is bad.

    An object naming a key twice is :class:`JsonDuplicateKeyError`, unless the reader passes
    ``object_pairs_hook`` (``json``'s) to see such keys itself (templates name each one as a
    problem); it gets every other check here all the same.
    """
    raw = document.encode() if isinstance(document, str) else document
    if exceeds_depth(raw, max_depth):
        raise JsonDepthError(max_depth)
    try:
        parsed = json.loads(
            raw,
            parse_int=_integer,
            parse_float=_real,
            parse_constant=_not_a_number,
            object_pairs_hook=object_pairs_hook or _unique_keys,
        )
    except RecursionError as exc:
        raise JsonDepthError(max_depth) from exc
    except JsonError:
        raise
    except ValueError as exc:  # JSONDecodeError and UnicodeDecodeError among others
        raise JsonError(f"not valid JSON: {exc}") from exc
    if SURROGATE_ESCAPE.search(raw) and _holds_lone_surrogate(parsed):
        raise JsonSurrogateError("a string holds a lone UTF-16 surrogate, which is not text")
    return parsed


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """An object's members as a dict, none named twice (about 10 % on a parse)."""
    members = dict(pairs)
    if len(members) != len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise JsonDuplicateKeyError(key)
            seen.add(key)
    return members


def _holds_lone_surrogate(document: Any) -> bool:
    """Whether any key or string in ``document`` holds a lone surrogate (a pair of escapes
    decodes to one character outside the range); only walked when the text has the escape."""
    pending = [document]
    while pending:
        value = pending.pop()
        if isinstance(value, str):
            if LONE_SURROGATE.search(value):
                return True
        elif isinstance(value, dict):
            pending.extend(value.keys())
            pending.extend(value.values())
        elif isinstance(value, list):
            pending.extend(value)
    return False


def _integer(digits: str) -> int:
    if len(digits.lstrip("-")) > MAX_INTEGER_DIGITS:
        raise JsonNumberError(f"an integer of more than {MAX_INTEGER_DIGITS} digits")
    return int(digits)


def _real(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise JsonNumberError(f"{text[:40]} is beyond the range of a double")
    return value


def _not_a_number(constant: str) -> Any:
    raise JsonNumberError(f"{constant} is not a JSON number")
