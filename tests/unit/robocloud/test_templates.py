"""The template and record wire format: every problem with its path, hostile inputs bounded."""

from __future__ import annotations

import json
from typing import Any

import pytest
import rfc8785
from hypothesis import given, settings
from hypothesis import strategies as st

from robocloud.bounded_json import JsonDepthError, JsonError, JsonSurrogateError
from robocloud.templates import (
    MAX_FIELDS,
    MAX_NESTING,
    ArrayOf,
    Container,
    RecordInvalid,
    Scalar,
    TemplateIdInvalid,
    TemplateInvalid,
    canonical_part,
    canonical_record,
    evaluate,
    load_template_document,
    parse_template,
    parse_template_id,
    validate_record,
)

ROBOT = "0x90F8bf6A479f320ead074411a4B0e7944Ea8c9C1"
CID_TEXT = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"

POSE: dict[str, Any] = {
    "name": "pose",
    "version": 1,
    "description": "where the robot is",
    "fields": {
        "frame": "string",
        "seq": "int",
        "ok": "bool",
        "pose": {
            "container": {
                "position": {"container": {"x": "float", "y": "float", "z": "float"}},
            }
        },
        "ranges": {"array": "float"},
        "camera": "image",
        "log": "file",
        "window": "range<int>",
        "band": "range<float>",
    },
}


def _data(**changes: Any) -> dict[str, Any]:
    data: dict[str, Any] = {
        "frame": "map",
        "seq": 3,
        "ok": True,
        "pose": {"position": {"x": 1.5, "y": -2, "z": 0.0}},
        "ranges": [0.5, 1.0],
        "camera": CID_TEXT,
        "log": CID_TEXT,
        "window": [1, 2],
        "band": [0.5, 0.5],
    }
    data.update(changes)
    return data


def _record(data: Any, **changes: Any) -> dict[str, Any]:
    record = {"template": "pose@1", "topic": "/pose", "robot": ROBOT, "t": 10, "data": data}
    record.update(changes)
    return record


def _problems(document: Any) -> dict[str, str]:
    template, problems = evaluate(document)
    assert template is None
    return {problem.path: problem.message for problem in problems}


def _nest(depth: int) -> Any:
    kind: Any = "int"
    for _ in range(depth):
        kind = {"array": kind}
    return kind


def test_a_clean_template_evaluates_to_its_types() -> None:
    template = parse_template(POSE)
    assert template.id == "pose@1"
    assert template.fields["pose"] == Container(
        {"position": Container({"x": Scalar("float"), "y": Scalar("float"), "z": Scalar("float")})}
    )
    assert template.fields["ranges"] == ArrayOf(Scalar("float"))
    assert template.to_json() == POSE
    assert dict(template.leaves())["pose.position.x"] == Scalar("float")
    assert "pose" not in dict(template.leaves())
    assert template.field_at("pose.position.y") == Scalar("float")
    assert template.field_at("pose.position") == template.fields["pose"].fields["position"]
    assert template.field_at("pose.nowhere") is None
    assert template.field_at("frame.x") is None
    assert template.field_at("ranges.0") is None


def test_every_problem_is_listed_with_its_path() -> None:
    document = {
        "name": "Bad-Name",
        "version": 0,
        "fields": {
            "ok": "int",
            "when": "datetime",
            "9lives": "int",
            "empty": {"container": {}},
            "pair": {"array": "int", "container": {"x": "int"}},
            "inner": {"container": {"Upper": "string", "deep": {"array": "vector"}}},
            "listed": ["int"],
        },
        "colour": "red",
    }
    assert _problems(document) == {
        "name": "required, must match [a-z][a-z0-9_]{0,62}",
        "version": "must be from 1 to 999999999",
        "fields.when": "unknown type datetime",
        "fields.9lives": "invalid name: must match [a-z][a-z0-9_]{0,62}",
        "fields.empty.container": "must hold at least one field",
        "fields.pair": 'a composite type is {"array": T} or {"container": ...}, not an object '
        "with array, container",
        "fields.inner.container.Upper": "invalid name: must match [a-z][a-z0-9_]{0,62}",
        "fields.inner.container.deep.array": "unknown type vector",
        "fields.listed": "a type is a name or an object, not a list",
        "colour": "unknown key (name, version, fields, description)",
    }
    with pytest.raises(TemplateInvalid) as caught:
        parse_template(document)
    assert len(caught.value.problems) == 10
    assert "and 9 more" in str(caught.value)


def test_duplicate_names_are_found_in_the_json_text() -> None:
    text = (
        '{"name": "dup", "version": 1, "fields": {"a": "int", "a": "float",'
        ' "c": {"container": {"x": "int", "x": "int"}}}}'
    )
    assert _problems(load_template_document(text)) == {
        "fields.a": "duplicate name",
        "fields.c.container.x": "duplicate name",
    }


def test_nesting_is_bounded_at_eight() -> None:
    parse_template({"name": "deep", "version": 1, "fields": {"x": _nest(MAX_NESTING)}})
    path = "fields.x" + ".array" * MAX_NESTING
    assert _problems({"name": "deep", "version": 1, "fields": {"x": _nest(MAX_NESTING + 1)}}) == {
        path: f"nesting deeper than {MAX_NESTING}"
    }


def test_a_hostile_deep_template_costs_no_recursion() -> None:
    problems = _problems({"name": "deep", "version": 1, "fields": {"x": _nest(100_000)}})
    assert list(problems.values()) == [f"nesting deeper than {MAX_NESTING}"]
    with pytest.raises(JsonDepthError):
        load_template_document('{"fields": {"x": ' + '{"array": ' * 100_000)


def test_a_huge_template_is_refused_once() -> None:
    fields = {f"f{index}": "int" for index in range(MAX_FIELDS + 10_000)}
    assert _problems({"name": "huge", "version": 1, "fields": fields}) == {
        "fields": f"more than {MAX_FIELDS} fields in the template"
    }


@pytest.mark.parametrize(
    ("document", "expected"),
    [
        ([], {"": "a template is an object, not a list"}),
        ("imu", {"": "a template is an object, not a string"}),
        (
            {"name": "x", "version": True, "fields": {"a": "int"}},
            {"version": "required, an integer from 1"},
        ),
        (
            {"name": "x", "version": 1.0, "fields": {"a": "int"}},
            {"version": "required, an integer from 1"},
        ),
        ({"name": "x", "version": 1}, {"fields": "required"}),
        ({"name": "x", "version": 1, "fields": {}}, {"fields": "must hold at least one field"}),
        (
            {"name": "x", "version": 1, "fields": [["a", "int"]]},
            {"fields": "must be an object of name: type, not a list"},
        ),
        (
            {"name": "x", "version": 1, "fields": {"a": None}},
            {"fields.a": "a type is a name or an object, not null"},
        ),
        (
            {"name": "x", "version": 1, "fields": {"a": "int"}, "description": 5},
            {"description": "must be a string"},
        ),
        (
            {"name": "x" * 64, "version": 1, "fields": {"a": "int"}},
            {"name": "required, must match [a-z][a-z0-9_]{0,62}"},
        ),
        (
            {"name": "x", "version": 1, "fields": {"a": "array<int>"}},
            {"fields.a": "unknown type array<int>"},
        ),
    ],
)
def test_wrong_types_are_named(document: Any, expected: dict[str, str]) -> None:
    assert _problems(document) == expected


def test_template_ids() -> None:
    assert parse_template_id("imu@12") == ("imu", 12)
    for bad in ("imu", "imu@0", "Imu@1", "imu@01", "imu@1@2", "imu@1234567890", ""):
        with pytest.raises(TemplateIdInvalid):
            parse_template_id(bad)


def test_a_valid_record_passes() -> None:
    template = parse_template(POSE)
    validate_record(template, _record(_data()))
    validate_record(template, _record(_data(ranges=CID_TEXT)))
    validate_record(template, _record(_data(ranges=[])))


@pytest.mark.parametrize(
    ("data", "path"),
    [
        (_data(pose={"position": {"x": "1", "y": 0, "z": 0}}), "data.pose.position.x"),
        (_data(pose={"position": {"x": True, "y": 0, "z": 0}}), "data.pose.position.x"),
        (_data(pose={"position": {"x": float("nan"), "y": 0, "z": 0}}), "data.pose.position.x"),
        (_data(pose={"position": {"x": float("inf"), "y": 0, "z": 0}}), "data.pose.position.x"),
        (_data(pose={"position": {"x": 1, "y": 0}}), "data.pose.position.z"),
        (_data(pose={"position": {"x": 1, "y": 0, "z": 0, "w": 1}}), "data.pose.position.w"),
        (_data(pose=[1, 2, 3]), "data.pose"),
        (_data(seq=True), "data.seq"),
        (_data(seq=1.5), "data.seq"),
        (_data(seq=2**53), "data.seq"),
        (_data(ok=1), "data.ok"),
        (_data(frame=7), "data.frame"),
        (_data(frame="x" * 65537), "data.frame"),
        (_data(frame="map\udc80"), "data.frame"),
        (_data(ranges=[0.1, "far"]), "data.ranges[1]"),
        (_data(ranges=[0.1, float("-inf")]), "data.ranges[1]"),
        (_data(ranges="not-a-cid"), "data.ranges"),
        (_data(ranges={"0": 1.0}), "data.ranges"),
        (_data(camera="Qm-nope"), "data.camera"),
        (_data(camera=5), "data.camera"),
        (_data(window=[3, 2]), "data.window"),
        (_data(window=[1, 2.5]), "data.window[1]"),
        (_data(window=[1]), "data.window"),
        (_data(band=[0.0, float("nan")]), "data.band[1]"),
        ([], "data"),
        (None, "data"),
    ],
)
def test_a_record_breaking_its_template_names_the_field(data: Any, path: str) -> None:
    with pytest.raises(RecordInvalid) as caught:
        validate_record(parse_template(POSE), _record(data))
    assert caught.value.path == path
    assert str(caught.value).startswith(f"{path}: ")
    with pytest.raises(RecordInvalid) as encoded:
        parse_template(POSE).encoder.canonical(_record(data))
    assert encoded.value.path == path


@pytest.mark.parametrize(
    ("changes", "path"),
    [
        ({"template": "pose@2"}, "template"),
        ({"template": "pose"}, "template"),
        ({"topic": "pose"}, "topic"),
        ({"topic": "/" + "x" * 300}, "topic"),
        ({"robot": ROBOT.lower()}, "robot"),
        ({"robot": 5}, "robot"),
        ({"t": -1}, "t"),
        ({"t": 2**63}, "t"),
        ({"t": True}, "t"),
        ({"t": 1.0}, "t"),
        ({"extra": 1}, "extra"),
    ],
)
def test_a_bad_envelope_names_its_key(changes: dict[str, Any], path: str) -> None:
    with pytest.raises(RecordInvalid) as caught:
        validate_record(parse_template(POSE), _record(_data(), **changes))
    assert caught.value.path == path


def test_a_missing_envelope_key_is_named() -> None:
    record = _record(_data())
    del record["robot"]
    with pytest.raises(RecordInvalid) as caught:
        validate_record(parse_template(POSE), record)
    assert caught.value.path == "robot"
    with pytest.raises(RecordInvalid) as caught:
        validate_record(parse_template(POSE), [record])
    assert caught.value.path == ""


def test_a_deep_value_is_checked_only_as_deep_as_the_template() -> None:
    template = parse_template({"name": "flat", "version": 1, "fields": {"x": {"array": "int"}}})
    deep: Any = 1
    for _ in range(100_000):
        deep = [deep]
    with pytest.raises(RecordInvalid) as caught:
        validate_record(template, _record({"x": deep}, template="flat@1"))
    assert caught.value.path == "data.x[0]"


def test_template_documents_refuse_nan() -> None:
    with pytest.raises(JsonError):
        load_template_document(json.dumps({"name": "x", "version": float("nan")}))


def test_text_with_a_lone_surrogate_is_no_template_and_no_record_string() -> None:
    """No UTF-8 answer, log line or canonical record can carry such a string."""
    with pytest.raises(JsonSurrogateError):
        load_template_document(
            b'{"name": "x", "fields": {"s": "string"}, "description": "\\udc80"}'
        )
    assert load_template_document(b'{"description": "\\ud83d\\ude00"}') == {
        "description": "\U0001f600"
    }
    assert _problems({**POSE, "description": "where\ud800"}) == {
        "description": "holds a lone UTF-16 surrogate, which is not text (no UTF-8 can carry it)"
    }
    template = parse_template(POSE)
    validate_record(template, _record(_data(frame="\u00e9t\u00e9 \U0001f600")))
    with pytest.raises(RecordInvalid) as caught:
        template.encoder.canonical(_record(_data(frame="\ud800")))
    assert caught.value.path == "data.frame"


FLOATS = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from([0.0, -0.0, 1e-6, 2.5e-6, 9.99e-7, 1e-7, 1e15, 1e16, 1e21, 2.0, -3.0, 5e-324]),
    st.integers(-(2**53) + 1, 2**53 - 1).map(float),
)
NUMBERS = st.one_of(FLOATS, st.integers(-(2**53) + 1, 2**53 - 1))
TEXTS = st.one_of(st.text(max_size=40), st.sampled_from(["1.0,", "[2.0]", "e+5", "-0.0", "null"]))


@st.composite
def pose_data(draw: st.DrawFn) -> dict[str, Any]:
    low = draw(st.integers(-(2**53) + 1, 2**53 - 11))
    band = sorted(draw(st.lists(FLOATS, min_size=2, max_size=2)))
    x, y, z = draw(st.tuples(NUMBERS, NUMBERS, NUMBERS))
    return _data(
        frame=draw(TEXTS),
        seq=draw(st.integers(-(2**53) + 1, 2**53 - 1)),
        ok=draw(st.booleans()),
        pose={"position": {"x": x, "y": y, "z": z}},
        ranges=draw(st.one_of(st.lists(NUMBERS, max_size=8), st.just(CID_TEXT))),
        window=[low, low + draw(st.integers(0, 10))],
        band=band,
    )


@settings(max_examples=400, deadline=None)
@given(pose_data(), st.integers(0, 2**63 - 1))
def test_the_encoder_writes_what_validate_and_canonical_write(data: Any, t: int) -> None:
    """The ingest fast path (orjson plus its rewrites) against the reference walk and RFC 8785."""
    record = _record(data, t=t)
    validate_record(parse_template(POSE), record)
    encoded = parse_template(POSE).encoder.canonical(record)
    assert encoded == canonical_record(record)
    assert rfc8785.dumps(data) in encoded


ECHOES = ArrayOf(Container({"echoes": ArrayOf(Scalar("float")), "ok": Scalar("bool")}))
"""A laser scan's ``ranges`` as its draft types them, a flag beside each beam's echoes."""
NAMED = ArrayOf(Container({"name": Scalar("string"), "x": Scalar("float")}))


@settings(max_examples=300, deadline=None)
@given(
    st.one_of(
        st.tuples(st.just(ArrayOf(Scalar("float"))), st.lists(NUMBERS, max_size=40)),
        st.tuples(st.just(ArrayOf(Scalar("int"))), st.lists(st.integers(-(2**53) + 1, 2**53 - 1))),
        st.tuples(st.just(ArrayOf(Scalar("file"))), st.lists(st.just(CID_TEXT), max_size=3)),
        st.tuples(
            st.just(ECHOES),
            st.lists(
                st.fixed_dictionaries(
                    {"echoes": st.lists(NUMBERS, max_size=4), "ok": st.booleans()}
                ),
                max_size=12,
            ),
        ),
        st.tuples(st.just(ArrayOf(Scalar("string"))), st.lists(TEXTS, max_size=6)),
        st.tuples(
            st.just(NAMED),
            st.lists(st.fixed_dictionaries({"name": TEXTS, "x": NUMBERS}), max_size=6),
        ),
    )
)
def test_a_part_of_checked_data_is_written_as_rfc8785_writes_it(
    kind_and_value: tuple[ArrayOf, list[Any]],
) -> None:
    """A large array a node moves to cas, through orjson where no string can hold ``.0``
    (``"1.0,"`` would lose its ``.0`` to the rewrite of integral floats), else the walk."""
    kind, value = kind_and_value
    assert canonical_part(value, kind) == rfc8785.dumps(value)
