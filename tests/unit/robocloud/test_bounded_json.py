"""Nesting is bounded before CPython's recursive decoder sees a document."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from robocloud.bounded_json import (
    JsonDepthError,
    JsonDuplicateKeyError,
    JsonError,
    JsonNumberError,
    JsonSurrogateError,
    exceeds_depth,
    loads,
)
from robocloud.errors import FormatError, RobocloudError


def nested(depth: int, open_: str = "[", close: str = "]") -> bytes:
    return (open_ * depth + close * depth).encode()


@pytest.mark.parametrize("depth", [1, 10, 63, 64])
def test_documents_within_the_bound_parse_as_json_does(depth: int) -> None:
    document = nested(depth)
    assert loads(document) == json.loads(document)


@pytest.mark.parametrize(
    "document",
    [
        nested(65),
        b'{"a":' * 65 + b"1" + b"}" * 65,
        b"[" * 100_000,
        b"[" * 100_000 + b"]" * 100_000,
        b"[{" * 40 + b"}]" * 40,
    ],
)
def test_deeper_documents_are_refused_before_parsing(document: bytes) -> None:
    with pytest.raises(JsonDepthError) as raised:
        loads(document)
    assert raised.value.max_depth == 64
    assert isinstance(raised.value, FormatError)
    assert isinstance(raised.value, RobocloudError)


def test_brackets_inside_strings_do_not_count() -> None:
    text = json.dumps({"s": "[" * 1000 + '\\"{' * 500, "list": [[1], [2], {"k": "]]]"}]})
    assert loads(text) == json.loads(text)


def test_many_shallow_containers_are_fine() -> None:
    document = json.dumps([{"a": [i, {"b": [i]}]} for i in range(10_000)]).encode()
    assert not exceeds_depth(document, 5)
    assert exceeds_depth(document, 4)
    assert loads(document, max_depth=5)[-1] == {"a": [9999, {"b": [9999]}]}


def test_mismatched_brackets_are_invalid_json_not_a_crash() -> None:
    for document in (b"[}" * 50_000, b"]" * 10 + b"[" * 10, b'{"a": [1}'):
        with pytest.raises(JsonError):
            loads(document)


def test_unclosed_brackets_count_towards_the_depth() -> None:
    assert exceeds_depth(b"[[]" + b"[" * 64, 64)
    assert not exceeds_depth(b"]" + b"[" * 100, 64)


def test_invalid_json_and_bad_encoding_are_json_errors() -> None:
    for document in (b"{", b"nan-ish", b"\xff\xfe\x00"):
        with pytest.raises(JsonError):
            loads(document)


def test_a_raised_recursion_limit_cannot_turn_depth_into_a_segfault() -> None:
    """py_ecc sets the recursion limit to 100,000; the bound must hold even then."""
    script = (
        "import sys; sys.setrecursionlimit(100_000)\n"
        "from robocloud.bounded_json import loads, JsonDepthError\n"
        "try:\n    loads(b'[' * 100_000 + b']' * 100_000)\n"
        "except JsonDepthError:\n    print('refused')\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == b"refused"


@pytest.mark.parametrize(
    "document",
    [
        b"NaN",
        b"[Infinity]",
        b'{"id": -Infinity}',
        b"9" * 1001,
        b"-" + b"9" * 5000,
        b"1e999",
        b"[-2.5E+400]",
    ],
)
def test_numbers_json_does_not_have_or_too_long_are_number_errors(document: bytes) -> None:
    with pytest.raises(JsonNumberError):
        loads(document)


def test_long_but_bounded_integers_and_floats_parse() -> None:
    assert loads(b"9" * 1000) == int("9" * 1000)
    assert loads(b"[1.5e3, -2]") == [1500.0, -2]


@pytest.mark.parametrize(
    "document",
    [rb'{"description": "\udc80"}', rb'{"\ud800": 1}', rb'[["x\uD800y"]]', rb'"\ude00\ud83d"'],
)
def test_strings_holding_a_lone_surrogate_are_refused(document: bytes) -> None:
    with pytest.raises(JsonSurrogateError):
        loads(document)


def test_surrogate_pairs_and_escaped_backslashes_are_text() -> None:
    assert loads(rb'{"a": "\ud83d\ude00"}') == {"a": "\N{GRINNING FACE}"}
    assert loads(rb'["\\ud800"]') == ["\\ud800"]


@pytest.mark.parametrize(
    ("document", "key"),
    [
        (b'{"challenge": "a", "challenge": "b"}', "challenge"),
        (b'[{"ok": 1}, {"deep": {"x": 1, "y": 2, "x": 3}}]', "x"),
        (b'{"\\u0061": 1, "a": 2}', "a"),
    ],
)
def test_an_object_naming_a_key_twice_is_refused_naming_it(document: bytes, key: str) -> None:
    """``json`` kept the last value: a signed body read one way here and another by a reader
    keeping the first, and a record's JCS hash was of a document I-JSON does not allow."""
    with pytest.raises(JsonDuplicateKeyError, match=f"the key '{key}' appears twice"):
        loads(document)


def test_a_reader_with_its_own_hook_sees_repeated_keys_itself() -> None:
    pairs = loads(b'{"a": 1, "a": 2}', object_pairs_hook=lambda found: found)
    assert pairs == [("a", 1), ("a", 2)]
