"""DAG-JSON links: the CIDs a dag-json block points to, found without building its values.

Pinning, garbage collection and ``dag/export`` follow a DAG whatever its codecs, as kubo's
recursive pin and ``dag export`` do (go-ipld-prime decodes dag-json links as it decodes
dag-cbor's). In dag-json a link is a map with the one key ``"/"`` whose value is the CID as
a string; ``{"/": {"bytes": ...}}`` is a byte string, not a link.

:func:`links` reads the JSON tokens in one pass with a stack of the open containers, so it
takes the nesting go-ipld-prime takes, 1,024 levels (its decoders' ``MaxDepth``), where
``json.loads`` recurses once per level in C and the services' recursion limit stops it
short of that. It refuses what is not dag-json (text that is not UTF-8, JSON's grammar
broken, a repeated map key, a lone surrogate, a number a 64-bit float cannot hold, as Go's
``strconv.ParseFloat`` under go-ipld-prime refuses it) but builds no values: strings are
read by ``json``'s own C scanner, and a number is converted only when it could overflow.
"""

from __future__ import annotations

import json.decoder
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from json.scanner import NUMBER_RE
from typing import NoReturn

from robocloud import bounded_json
from robocloud.cid import CID, CIDError, parse_cid
from robocloud.errors import FormatError

MAX_DEPTH = 1024
"""go-ipld-prime's default ``MaxDepth`` for dag-json and dag-cbor, which kubo decodes with."""

_scan_string: Callable[[str, int, bool], tuple[str, int]] = json.decoder.scanstring  # type: ignore[attr-defined]
"""``json``'s string reader (C): the text from after an opening quote to its closing one,
unescaped, and where it ended; typeshed does not list it."""
_FLOAT_DIGITS = 308
"""A number with no exponent and no more integer digits than this fits a 64-bit float, so it
is not converted to check."""
_WHITESPACE = re.compile(r"[ \t\n\r]*")
_LITERALS = ("true", "false", "null")


class DagJsonError(FormatError):
    """Bytes that are not dag-json: not JSON, nested past the bound, or a bad link."""


@dataclass
class _Map:
    """An open map: its keys so far, and its ``"/"`` value when that is a string."""

    keys: set[str] = field(default_factory=set)
    key: str = ""
    slash: str | None = None


class _List:
    """An open list."""


def links(data: bytes) -> list[CID]:
    """The CIDs ``data`` links to, in document order (a repeated link every time)."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DagJsonError(f"not dag-json: not UTF-8 text ({exc})") from exc
    try:
        return _Scan(text, bounded_json.SURROGATE_ESCAPE.search(data) is not None).links()
    except json.JSONDecodeError as exc:  # from the string reader
        raise DagJsonError(f"not dag-json: {exc}") from exc


class _Scan:
    def __init__(self, text: str, escapes_surrogates: bool) -> None:
        self.text = text
        self.escapes_surrogates = escapes_surrogates
        """Whether a string may hold a lone surrogate (only an escape can make one)."""
        self.pos = 0
        self.open: list[_Map | _List] = []
        self.found: list[CID] = []

    def links(self) -> list[CID]:
        self._skip_whitespace()
        while True:
            value = self._value()
            while value is not None:
                if not self.open:
                    self._skip_whitespace()
                    if self.pos != len(self.text):
                        self._fail("data after the document")
                    return self.found
                value = self._after_value(value)

    def _value(self) -> str | bool | None:
        """Read a value, or open a container; the value read (a string, or False for any
        other), or None when a container was opened and its first value comes next."""
        char = self.text[self.pos : self.pos + 1]
        if char in ("{", "["):
            if len(self.open) >= MAX_DEPTH:
                raise DagJsonError(f"not dag-json: nested deeper than {MAX_DEPTH} levels")
            self.pos += 1
            self._skip_whitespace()
            if char == "{":
                self.open.append(_Map())
                if self._take("}"):
                    return self._close()
                self._key()
            else:
                self.open.append(_List())
                if self._take("]"):
                    return self._close()
            return None
        if char == '"':
            return self._string()
        number = NUMBER_RE.match(self.text, self.pos)
        if number is not None:
            integer, _, exponent = number.groups()
            if (exponent or len(integer) > _FLOAT_DIGITS) and math.isinf(float(number.group())):
                self._fail("a number beyond the range of a 64-bit float")
            self.pos = number.end()
            return False
        for literal in _LITERALS:
            if self.text.startswith(literal, self.pos):
                self.pos += len(literal)
                return False
        self._fail("expected a value")

    def _after_value(self, value: str | bool) -> str | bool | None:
        """Give ``value`` to the innermost container, then read what follows it: a comma
        (None: the next value comes) or the container's end (the container, as a value)."""
        container = self.open[-1]
        if isinstance(container, _Map) and container.key == "/" and isinstance(value, str):
            container.slash = value
        self._skip_whitespace()
        if self._take(","):
            self._skip_whitespace()
            if isinstance(container, _Map):
                self._key()
            return None
        if self._take("}" if isinstance(container, _Map) else "]"):
            return self._close()
        self._fail("expected ',' or the end of the " + type(container).__name__[1:].lower())

    def _close(self) -> bool:
        container = self.open.pop()
        if isinstance(container, _Map) and container.keys == {"/"} and container.slash is not None:
            self.found.append(_link(container.slash))
        return False

    def _key(self) -> None:
        if not self.text.startswith('"', self.pos):
            self._fail("expected a map key")
        key = self._string()
        container = self.open[-1]
        assert isinstance(container, _Map)
        if key in container.keys:
            self._fail(f"repeated map key {key[:40]!r}")
        container.keys.add(key)
        container.key = key
        self._skip_whitespace()
        if not self._take(":"):
            self._fail("expected ':' after a map key")
        self._skip_whitespace()

    def _string(self) -> str:
        value, self.pos = _scan_string(self.text, self.pos + 1, True)
        if self.escapes_surrogates and bounded_json.LONE_SURROGATE.search(value):
            self._fail("a string holds a lone UTF-16 surrogate, which is not text")
        return value

    def _take(self, char: str) -> bool:
        if self.text.startswith(char, self.pos):
            self.pos += 1
            return True
        return False

    def _skip_whitespace(self) -> None:
        match = _WHITESPACE.match(self.text, self.pos)
        assert match is not None  # the pattern matches the empty string
        self.pos = match.end()

    def _fail(self, what: str) -> NoReturn:
        raise DagJsonError(f"not dag-json: {what} at character {self.pos}")


def _link(text: str) -> CID:
    try:
        return parse_cid(text)
    except CIDError as exc:
        raise DagJsonError(f"a link that is not a CID: {exc}") from exc
