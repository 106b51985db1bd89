"""RFC 8785 canonical JSON against the RFC's own examples."""

from __future__ import annotations

import json
import struct

import pytest
import rfc8785
from hypothesis import given, settings
from hypothesis import strategies as st

from robocloud.bounded_json import JsonDepthError
from robocloud.errors import FormatError
from robocloud.jcs import JcsError, canonical, canonicalize

# RFC 8785 Appendix B: IEEE 754 doubles (hex) and their ECMAScript serialisation.
NUMBERS = [
    ("0000000000000000", "0"),
    ("8000000000000000", "0"),
    ("0000000000000001", "5e-324"),
    ("8000000000000001", "-5e-324"),
    ("7fefffffffffffff", "1.7976931348623157e+308"),
    ("ffefffffffffffff", "-1.7976931348623157e+308"),
    ("4340000000000000", "9007199254740992"),
    ("c340000000000000", "-9007199254740992"),
    ("4430000000000000", "295147905179352830000"),
    ("44b52d02c7e14af5", "9.999999999999997e+22"),
    ("44b52d02c7e14af6", "1e+23"),
    ("44b52d02c7e14af7", "1.0000000000000001e+23"),
    ("444b1ae4d6e2ef4e", "999999999999999700000"),
    ("444b1ae4d6e2ef4f", "999999999999999900000"),
    ("444b1ae4d6e2ef50", "1e+21"),
    ("3eb0c6f7a0b5ed8c", "9.999999999999997e-7"),
    ("3eb0c6f7a0b5ed8d", "0.000001"),
    ("41b3de4355555553", "333333333.3333332"),
    ("41b3de4355555554", "333333333.33333325"),
    ("41b3de4355555555", "333333333.3333333"),
    ("41b3de4355555556", "333333333.3333334"),
    ("41b3de4355555557", "333333333.33333343"),
    ("becbf647612f3696", "-0.0000033333333333333333"),
    ("43143ff3c1cb0959", "1424953923781206.2"),
]


@pytest.mark.parametrize(("ieee", "expected"), NUMBERS)
def test_numbers_serialise_as_appendix_b(ieee: str, expected: str) -> None:
    (value,) = struct.unpack(">d", bytes.fromhex(ieee))
    assert canonical(value) == expected.encode()


@pytest.mark.parametrize("ieee", ["7fffffffffffffff", "7ff0000000000000", "fff0000000000000"])
def test_nan_and_infinities_are_refused(ieee: str) -> None:
    (value,) = struct.unpack(">d", bytes.fromhex(ieee))
    with pytest.raises(JcsError):
        canonical(value)


def test_the_section_3_2_2_example() -> None:
    document = (
        '{"numbers": [333333333.33333329, 1E30, 4.50, 2e-3, 0.000000000000000000000000001],'
        ' "string": "\\u20ac$\\u000F\\u000aA\'\\u0042\\u0022\\u005c\\\\\\"\\/",'
        ' "literals": [null, true, false]}'
    )
    assert (
        canonicalize(document)
        == (
            '{"literals":[null,true,false],"numbers":[333333333.3333333,1e+30,4.5,0.002,1e-27],'
            '"string":"€$\\u000f\\nA\'B\\"\\\\\\\\\\"/"}'
        ).encode()
    )


def test_the_section_3_2_3_sorting_example() -> None:
    document = json.dumps(
        {
            "\u20ac": "Euro Sign",
            "\r": "Carriage Return",
            "\ufb33": "Hebrew Letter Dalet With Dagesh",
            "1": "One",
            "\U0001f600": "Emoji: Grinning Face",
            "\u0080": "Control",
            "\u00f6": "Latin Small Letter O With Diaeresis",
        }
    )
    keys = list(json.loads(canonicalize(document)))
    assert keys == ["\r", "1", "\u0080", "\u00f6", "\u20ac", "\U0001f600", "\ufb33"]


def test_unsafe_integers_and_non_json_values_are_jcs_errors() -> None:
    for value in (2**60, {1: "int key"}, {"set": {1, 2}}, b"bytes"):
        with pytest.raises(JcsError) as raised:
            canonical(value)
        assert isinstance(raised.value, FormatError)


def test_deep_documents_are_refused_before_canonicalization() -> None:
    with pytest.raises(JsonDepthError):
        canonicalize(b"[" * 10_000 + b"]" * 10_000)


@pytest.mark.parametrize(
    "document",
    [
        '{"numbers": [333333333.33333329, 1E30, 4.50, 2e-3], "string": "\\u20ac$\\u000F\\u000aA"}',
        '{"\\u20ac": 1, "\\r": [true, null, {"b": -0.0, "a": 9007199254740991}], "\\ufb33": 2}',
    ],
)
def test_exact_integers_change_nothing_inside_rfc_8785s_domain(document: str) -> None:
    value = json.loads(document)
    assert canonical(value, exact_integers=True) == canonical(value)


def test_exact_integers_keep_every_digit_of_a_nanosecond_time() -> None:
    one, two = 1_700_000_000_123_456_789, 1_700_000_000_123_456_790
    assert canonical({"t": one}, exact_integers=True) == b'{"t":1700000000123456789}'
    assert canonical({"t": one}, exact_integers=True) != canonical({"t": two}, exact_integers=True)
    assert json.loads(canonical({"t": -(2**63)}, exact_integers=True)) == {"t": -(2**63)}
    for value in ({1: "int key"}, [float("nan")], b"bytes", [[[]]] * 1 + [{"x": {1, 2}}]):
        with pytest.raises(JcsError):
            canonical(value, exact_integers=True)


def test_exact_integers_bound_the_nesting() -> None:
    deep: list[object] = []
    for _ in range(100):
        deep = [deep]
    with pytest.raises(JcsError, match="nested deeper"):
        canonical(deep, exact_integers=True)


@settings(max_examples=3000, deadline=None)
@given(st.floats(allow_nan=False, allow_infinity=False))
def test_numbers_agree_with_the_rfc8785_package(value: float) -> None:
    assert canonical(value) == rfc8785.dumps(value)


JSON_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**53) + 1, 2**53 - 1)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(), children, max_size=5)
    ),
    max_leaves=30,
)


@settings(max_examples=1000, deadline=None)
@given(JSON_VALUES)
def test_documents_agree_with_the_rfc8785_package(value: object) -> None:
    """The reference implementation on the same values: key order by UTF-16 code units,
    string escapes, numbers; a lone surrogate is refused by both."""
    try:
        expected = rfc8785.dumps(value)
    except rfc8785.CanonicalizationError:
        with pytest.raises(JcsError):
            canonical(value)
        return
    assert canonical(value) == expected
    assert canonical(value, exact_integers=True) == expected
