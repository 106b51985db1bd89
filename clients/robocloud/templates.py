"""Templates and records: the typed wire format of robocloud's storage, shared by robots and nodes.

A template ``{"name", "version", "fields", "description"}`` types a record's ``data``; its id
is ``name@version``. :func:`evaluate` returns *every* problem of a template document with its
path, so that a designer fixes them in one round; :func:`parse_template` turns a clean one
into a :class:`Template`. :func:`validate_record` checks a record against its template and
raises :class:`RecordInvalid` naming the first offending field path (``data.pose.position.x``,
``data.ranges[3]``). Both walk only as deep as a template may nest (8), so a hostile document
costs at most its size, never a stack overflow.

The module is pure: no I/O, no HTTP. The storage service and the SDK use the same code, so a
robot can check its records before it sends them.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any, Literal, NoReturn

import orjson
from eth_utils.address import is_checksum_address

from robocloud import bounded_json, jcs
from robocloud.cid import CIDError, parse_cid
from robocloud.errors import FormatError
from robocloud.jcs import MAX_SAFE_INTEGER

NAME = re.compile(r"[a-z][a-z0-9_]{0,62}")
"""Template and field names."""
TEMPLATE_ID = re.compile(r"([a-z][a-z0-9_]{0,62})@([1-9][0-9]{0,8})")
MAX_NESTING = 8
"""Arrays and containers inside one another, at most."""
MAX_FIELDS = 1024
"""Fields of one template, counted through every container."""
MAX_VERSION = 10**9 - 1
MAX_DESCRIPTION = 4096
MAX_TOPIC = 256
MAX_STRING = 65536
"""Characters of one string value."""
MAX_T = 2**63 - 1
MAX_PROBLEMS = 200
"""Problems listed for one template; a document with more is hopeless anyway."""
TOPIC = re.compile(r"/[A-Za-z0-9_/~.-]{0,255}")
RECORD_KEYS = ("template", "topic", "robot", "t", "data")

ScalarKind = Literal[
    "string", "int", "float", "bool", "image", "file", "range<int>", "range<float>"
]
SCALAR_KINDS: frozenset[str] = frozenset(
    ("string", "int", "float", "bool", "image", "file", "range<int>", "range<float>")
)
TEMPLATE_KEYS = frozenset(("name", "version", "fields", "description"))


class TemplateInvalid(FormatError):
    """A template document with problems; ``problems`` lists each with its path."""

    def __init__(self, problems: list[Problem]) -> None:
        first = problems[0]
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        super().__init__(f"invalid template: {first.path}: {first.message}{more}")
        self.problems = problems


class TemplateIdInvalid(FormatError):
    """Text that is not a template id ``name@version``."""

    def __init__(self, text: str) -> None:
        super().__init__(f"{text[:80]!r} is not a template id (name@version)")
        self.text = text


class RecordInvalid(FormatError):
    """A record that breaks its template or the record format; ``path`` names the field."""

    def __init__(self, path: str, message: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = path
        self.reason = message


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a template document, at ``path`` (``fields.pose.container.x``)."""

    path: str
    message: str

    def to_json(self) -> dict[str, str]:
        return {"path": self.path, "message": self.message}


@dataclass(frozen=True)
class Scalar:
    kind: ScalarKind


@dataclass(frozen=True)
class ArrayOf:
    item: FieldType


@dataclass(frozen=True)
class Container:
    fields: Mapping[str, FieldType]


FieldType = Scalar | ArrayOf | Container


@dataclass(frozen=True)
class Template:
    """An evaluated template: its fields typed, its id ``name@version``."""

    name: str
    version: int
    fields: Mapping[str, FieldType]
    description: str = ""

    @cached_property
    def id(self) -> str:
        """Read for every record ingested: made once."""
        return f"{self.name}@{self.version}"

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "version": self.version,
            "fields": {name: type_to_json(kind) for name, kind in self.fields.items()},
            "description": self.description,
        }

    @cached_property
    def encoder(self) -> RecordEncoder:
        """Compiled once per template object, on first use."""
        return RecordEncoder(self)

    def leaves(self) -> Iterator[tuple[str, FieldType]]:
        """Every field reachable through containers only, by dotted path (``pose.position.x``).

        Arrays are leaves (their items have no path of their own); containers are not.
        """
        stack: list[tuple[str, Mapping[str, FieldType]]] = [("", self.fields)]
        while stack:
            prefix, fields = stack.pop()
            for name, kind in fields.items():
                path = f"{prefix}{name}"
                if isinstance(kind, Container):
                    stack.append((f"{path}.", kind.fields))
                else:
                    yield path, kind

    def field_at(self, path: str) -> FieldType | None:
        """The type of the field at dotted ``path`` (a leaf or a container), None when
        there is none: an array's items have no path."""
        kind: FieldType | None = None
        fields: Mapping[str, FieldType] | None = self.fields
        for part in path.split("."):
            if fields is None:
                return None
            kind = fields.get(part)
            if kind is None:
                return None
            fields = kind.fields if isinstance(kind, Container) else None
        return kind


def type_to_json(kind: FieldType) -> Any:
    if isinstance(kind, Scalar):
        return kind.kind
    if isinstance(kind, ArrayOf):
        return {"array": type_to_json(kind.item)}
    return {"container": {name: type_to_json(inner) for name, inner in kind.fields.items()}}


def parse_template_id(text: str) -> tuple[str, int]:
    """``imu@1`` as ``("imu", 1)``; :class:`TemplateIdInvalid` otherwise."""
    match = TEMPLATE_ID.fullmatch(text) if isinstance(text, str) else None
    if match is None:
        raise TemplateIdInvalid(str(text))
    return match.group(1), int(match.group(2))


class _Pairs(dict[str, Any]):
    """A JSON object that remembers the keys it held more than once."""

    duplicates: tuple[str, ...] = ()


def _object_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    result = _Pairs(pairs)
    if len(result) != len(pairs):
        seen: set[str] = set()
        duplicates: list[str] = []
        for key, _ in pairs:
            if key in seen:
                duplicates.append(key)
            seen.add(key)
        result.duplicates = tuple(duplicates)
    return result


def load_template_document(document: bytes | str) -> Any:
    """Parse a template's JSON keeping track of duplicate names, which ``json`` would drop.

    :func:`robocloud.bounded_json.loads` checks the nesting first (without recursion) and
    refuses what no template may hold: a string with a lone surrogate (a description
    ``"\\udc80"`` was stored, then every answer that rendered it failed), NaN, huge numbers.
    """
    return bounded_json.loads(
        document, max_depth=2 * (MAX_NESTING + 2) + 2, object_pairs_hook=_object_pairs
    )


class _Evaluator:
    def __init__(self) -> None:
        self.problems: list[Problem] = []
        self.field_count = 0

    def problem(self, path: str, message: str) -> None:
        if len(self.problems) < MAX_PROBLEMS:
            self.problems.append(Problem(path, message))

    def type_of(self, value: Any, path: str, depth: int) -> FieldType | None:
        if isinstance(value, str):
            if value in SCALAR_KINDS:
                return Scalar(value)  # type: ignore[arg-type]
            self.problem(path, f"unknown type {_shown(value)}")
            return None
        if not isinstance(value, dict):
            self.problem(path, f"a type is a name or an object, not {_kind_of(value)}")
            return None
        if len(value) != 1 or next(iter(value)) not in ("array", "container"):
            keys = ", ".join(_shown(key) for key in list(value)[:5])
            self.problem(
                path,
                f'a composite type is {{"array": T}} or {{"container": ...}}, '
                f"not an object with {keys or 'no keys'}",
            )
            return None
        if depth > MAX_NESTING:
            self.problem(path, f"nesting deeper than {MAX_NESTING}")
            return None
        composite, inner = next(iter(value.items()))
        if composite == "array":
            item = self.type_of(inner, f"{path}.array", depth + 1)
            return ArrayOf(item) if item is not None else None
        fields = self.fields_of(inner, f"{path}.container", depth)
        return Container(fields) if fields is not None else None

    def fields_of(self, value: Any, path: str, depth: int) -> dict[str, FieldType] | None:
        """The ``NAME: TYPE`` object at ``path``, inside ``depth`` composite types."""
        if not isinstance(value, dict):
            self.problem(path, f"must be an object of name: type, not {_kind_of(value)}")
            return None
        for duplicate in getattr(value, "duplicates", ()):
            self.problem(f"{path}.{_shown(duplicate)}", "duplicate name")
        if not value:
            self.problem(path, "must hold at least one field")
            return None
        fields: dict[str, FieldType] = {}
        for name, kind in value.items():
            self.field_count += 1
            if self.field_count > MAX_FIELDS:
                self.problem(path, f"more than {MAX_FIELDS} fields in the template")
                return None
            field_path = f"{path}.{_shown(name)}"
            if not NAME.fullmatch(name):
                self.problem(field_path, "invalid name: must match [a-z][a-z0-9_]{0,62}")
            parsed = self.type_of(kind, field_path, depth + 1)
            if parsed is not None:
                fields[name] = parsed
        return fields


NOT_TEXT = "holds a lone UTF-16 surrogate, which is not text (no UTF-8 can carry it)"


def _not_text(value: str) -> bool:
    """Whether ``value`` holds half of a surrogate pair, as ``os.fsdecode`` makes of a file
    name that is not UTF-8: JSON's escapes carry it, but no canonical record or answer can
    be encoded with it, and RFC 7493 (I-JSON) forbids it."""
    return bounded_json.LONE_SURROGATE.search(value) is not None


def _shown(value: str) -> str:
    return value if len(value) <= 80 else f"{value[:77]}..."


def _kind_of(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int | float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def evaluate(document: Any) -> tuple[Template | None, list[Problem]]:
    """Every problem of a template document with its path, and the template when there are none."""
    evaluator = _Evaluator()
    if not isinstance(document, dict):
        return None, [Problem("", f"a template is an object, not {_kind_of(document)}")]
    for duplicate in getattr(document, "duplicates", ()):
        evaluator.problem(duplicate, "duplicate key")
    for key in document:
        if key not in TEMPLATE_KEYS:
            evaluator.problem(_shown(key), "unknown key (name, version, fields, description)")
    name = document.get("name")
    if not isinstance(name, str) or not NAME.fullmatch(name):
        evaluator.problem("name", "required, must match [a-z][a-z0-9_]{0,62}")
    version = document.get("version")
    if isinstance(version, bool) or not isinstance(version, int):
        evaluator.problem("version", "required, an integer from 1")
    elif not 1 <= version <= MAX_VERSION:
        evaluator.problem("version", f"must be from 1 to {MAX_VERSION}")
    description = document.get("description", "")
    if not isinstance(description, str):
        evaluator.problem("description", "must be a string")
    elif len(description) > MAX_DESCRIPTION:
        evaluator.problem("description", f"longer than {MAX_DESCRIPTION} characters")
    elif _not_text(description):
        evaluator.problem("description", NOT_TEXT)
    if "fields" not in document:
        evaluator.problem("fields", "required")
        fields = None
    else:
        fields = evaluator.fields_of(document["fields"], "fields", 0)
    if evaluator.problems or fields is None:
        return None, evaluator.problems
    assert isinstance(name, str)
    assert isinstance(version, int)
    assert isinstance(description, str)
    return Template(name, version, fields, description), []


def parse_template(document: Any) -> Template:
    """The template of a clean document; :class:`TemplateInvalid` listing every problem."""
    template, problems = evaluate(document)
    if template is None:
        raise TemplateInvalid(problems)
    return template


def _join(path: str, name: str) -> str:
    return f"{path}.{name}"


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _check(kind: FieldType, value: Any, path: str) -> None:
    """Raise :class:`RecordInvalid` at the first place ``value`` breaks ``kind``.

    Recursion follows the template, at most ``MAX_NESTING`` deep, never the value.
    """
    if isinstance(kind, Scalar):
        _check_scalar(kind.kind, value, path)
    elif isinstance(kind, ArrayOf):
        if isinstance(value, str):
            _cid(value, path, "an array, or the CID of one stored in cas")
            return
        if not isinstance(value, list):
            raise RecordInvalid(path, f"must be an array, not {_kind_of(value)}")
        for index, item in enumerate(value):
            _check(kind.item, item, f"{path}[{index}]")
    else:
        check_container(kind.fields, value, path)


def check_container(fields: Mapping[str, FieldType], value: Any, path: str) -> None:
    if not isinstance(value, dict):
        raise RecordInvalid(path, f"must be an object, not {_kind_of(value)}")
    for name in value:
        if name not in fields:
            shown = _shown(name) if isinstance(name, str) else repr(name)
            raise RecordInvalid(_join(path, shown), "not a field of the template")
    for name, kind in fields.items():
        if name not in value:
            raise RecordInvalid(_join(path, name), "missing")
        _check(kind, value[name], _join(path, name))


def _cid(value: str, path: str, expected: str) -> None:
    try:
        parse_cid(value, path)
    except CIDError as exc:
        raise RecordInvalid(path, f"must be {expected}: {exc}") from exc


def _check_scalar(kind: str, value: Any, path: str) -> None:
    if kind == "string":
        if not isinstance(value, str):
            raise RecordInvalid(path, f"must be a string, not {_kind_of(value)}")
        if len(value) > MAX_STRING:
            raise RecordInvalid(path, f"longer than {MAX_STRING} characters")
        if _not_text(value):
            raise RecordInvalid(path, NOT_TEXT)
    elif kind == "int":
        _check_int(value, path)
    elif kind == "float":
        _check_float(value, path)
    elif kind == "bool":
        if not isinstance(value, bool):
            raise RecordInvalid(path, f"must be true or false, not {_kind_of(value)}")
    elif kind in ("image", "file"):
        if not isinstance(value, str):
            raise RecordInvalid(path, f"must be a CID string, not {_kind_of(value)}")
        _cid(value, path, "a CID")
    else:
        if not isinstance(value, list) or len(value) != 2:
            raise RecordInvalid(path, "must be a range [low, high]")
        check = _check_int if kind == "range<int>" else _check_float
        check(value[0], f"{path}[0]")
        check(value[1], f"{path}[1]")
        if value[0] > value[1]:
            raise RecordInvalid(path, "low is above high")


def _check_int(value: Any, path: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise RecordInvalid(path, f"must be an integer, not {_kind_of(value)}")
    if abs(value) > MAX_SAFE_INTEGER:
        raise RecordInvalid(path, "an integer beyond +-(2**53 - 1) (I-JSON)")


def _check_float(value: Any, path: str) -> None:
    if not _number(value):
        raise RecordInvalid(path, f"must be a number, not {_kind_of(value)}")
    if isinstance(value, float) and not math.isfinite(value):
        raise RecordInvalid(path, "must be finite (no NaN or infinity)")
    if isinstance(value, int) and abs(value) > MAX_SAFE_INTEGER:
        raise RecordInvalid(path, "an integer beyond +-(2**53 - 1) (I-JSON)")


def validate_data(template: Template, data: Any, path: str = "data") -> None:
    """Check ``data`` against ``template``'s fields; :class:`RecordInvalid` names the path.

    Plain valid data (nearly all of it, at ingestion's rate) is accepted by the template's
    compiled encoder, which builds no path strings; whatever it does not take at once (a
    subclass, a problem) is checked by the walk that names the problem.
    """
    try:
        template.encoder.check_data(data)
    except Irregular:
        check_container(template.fields, data, path)


class Irregular(FormatError):
    """A value the compiled check leaves to the walk that names problems, and to
    :mod:`robocloud.jcs`: a problem, a subclass of a JSON type, a string :class:`RecordEncoder`
    could not tell from a number's text."""


def _irregular() -> NoReturn:
    raise Irregular


Check = Callable[[Any], None]
"""Returns if a value certainly conforms to the kind it was compiled for; raises
:class:`Irregular` otherwise, building no path strings."""


def _check_number(value: Any) -> None:
    kind = type(value)
    if not (
        (kind is float and value - value == 0.0)
        or (kind is int and -MAX_SAFE_INTEGER <= value <= MAX_SAFE_INTEGER)
    ):
        _irregular()


def _check_integer(value: Any) -> None:
    if not (type(value) is int and -MAX_SAFE_INTEGER <= value <= MAX_SAFE_INTEGER):
        _irregular()


def _check_string(value: Any) -> None:
    """``.0`` is refused here only so that :class:`RecordEncoder` may rewrite a float's
    ``.0,`` in the text outside strings: such a string takes the slower, exact path."""
    if not (
        type(value) is str
        and len(value) <= MAX_STRING
        and ".0" not in value
        and (value.isascii() or not _not_text(value))
    ):
        _irregular()


def _check_bool(value: Any) -> None:
    if type(value) is not bool:
        _irregular()


def _check_cid(value: Any) -> None:
    if type(value) is not str:
        _irregular()
    try:
        parse_cid(value)
    except CIDError:
        _irregular()


def _range_check(bound: Check) -> Check:
    def check(value: Any) -> None:
        if type(value) is not list or len(value) != 2:
            _irregular()
        bound(value[0])
        bound(value[1])
        if value[0] > value[1]:
            _irregular()

    return check


_SCALAR_CHECKS: dict[str, Check] = {
    "string": _check_string,
    "int": _check_integer,
    "float": _check_number,
    "bool": _check_bool,
    "image": _check_cid,
    "file": _check_cid,
    "range<int>": _range_check(_check_integer),
    "range<float>": _range_check(_check_number),
}
_FLOAT_ONLY = frozenset((float,))


def finite_floats(values: list[Any]) -> bool:
    """Whether every item is a finite float, in two C loops instead of a call per item: a
    sum is finite only if every term is (covariances and ranges are read this way)."""
    return _FLOAT_ONLY.issuperset(map(type, values)) and math.isfinite(sum(values))


def _compile(kind: FieldType) -> Check:
    if isinstance(kind, Scalar):
        return _SCALAR_CHECKS[kind.kind]
    if isinstance(kind, ArrayOf):
        return _array_check(_compile(kind.item))
    return _container_check(kind.fields)


def _array_check(item: Check) -> Check:
    floats = item is _check_number

    def check(value: Any) -> None:
        if type(value) is not list:
            _check_cid(value)
        elif not (floats and finite_floats(value)):
            for element in value:
                item(element)

    return check


def _container_check(fields: Mapping[str, FieldType]) -> Check:
    members = [(name, _compile(kind)) for name, kind in fields.items()]
    count = len(members)

    def check(value: Any) -> None:
        if type(value) is not dict or len(value) != count:
            _irregular()
        try:
            for name, member in members:
                member(value[name])
        except KeyError:
            _irregular()

    return check


def _not_ecmascript(text: bytes) -> bool:
    """Whether orjson's number text may differ from ECMAScript's here: exponents from 1e16 up,
    the 1e-6 decade, and negative zero (``-0.0`` ending where its value does, unlike -0.01).
    Checked data holds no NaN or infinity, which orjson would write as null."""
    if b"e+" in text or b"e-6" in text:
        return True
    return b"-0.0" in text and (b"-0.0," in text or b"-0.0]" in text or b"-0.0}" in text)


_INTEGRAL = re.compile(rb"\.0(?=[,\]}])")
"""The ``.0`` of an integral float, which ECMAScript does not write (``2.0`` is ``2``)."""


class RecordEncoder:
    """A template compiled into a check of records, and their canonical bytes through orjson.

    ``canonical(record)`` equals :func:`validate_record` followed by :func:`canonical_record`
    (the tests hold it to both, and to the ``rfc8785`` package), at a fraction of their cost:
    ingestion does both for every record. Once the check has passed, orjson writes ``data``
    with sorted keys (field names are ASCII, so code points and UTF-16 units sort alike) and
    RFC 8785's string escapes; its shortest float digits are ECMAScript's, in the same layout
    except for integral floats (``2.0``, rewritten ``2``) and the cases in
    ``_not_ecmascript``, which :mod:`robocloud.jcs` writes instead. Checked strings never hold
    ``.0``, so the rewrite touches numbers only.
    """

    def __init__(self, template: Template) -> None:
        self.template = template
        self.check_data: Check = _container_check(template.fields)
        """Returns for conforming ``data``; raises :class:`Irregular` otherwise."""

    def canonical(self, record: Any) -> bytes:
        """The record's canonical bytes; :class:`RecordInvalid` names what breaks the template."""
        template_id = check_envelope(record)
        if template_id != self.template.id:
            raise RecordInvalid("template", f"is {template_id}, expected {self.template.id}")
        return self.canonical_enveloped(record)

    def canonical_enveloped(self, record: dict[str, Any]) -> bytes:
        """:meth:`canonical` of a record whose envelope :func:`check_envelope` has passed and
        names this template: the caller looked its template up by that check."""
        template_id = self.template.id
        data = record["data"]
        try:
            self.check_data(data)
        except Irregular:
            text = None
        else:
            text = _through_orjson(data)
        if text is None:
            check_container(self.template.fields, data, "data")
            return canonical_record(record)
        t = record["t"]
        return b'{"data":%s,"robot":"%s","t":%d,"template":"%s","topic":"%s"}' % (
            text,
            record["robot"].encode(),
            t,
            template_id.encode(),
            record["topic"].encode(),
        )


def canonical_part(value: Any, kind: FieldType) -> bytes:
    """The RFC 8785 bytes of ``value``, a part of type ``kind`` of record data that its
    template's check has passed (a large array a node moves to cas).

    Written by orjson as :class:`RecordEncoder` writes ``data`` when no string of ``kind`` may
    hold ``.0`` (numbers, booleans, CIDs and containers of them, whose field names never do),
    by :mod:`robocloud.jcs` otherwise: a laser scan's thousand echoes took 10 ms a message
    through jcs, more than the rest of its ingestion.
    """
    text = None if _holds_text(kind) else _through_orjson(value)
    return jcs.canonical(value) if text is None else text


def _through_orjson(checked: Any) -> bytes | None:
    """The RFC 8785 bytes of a value whose strings hold no ``.0`` and whose numbers are
    finite, I-JSON ones, as orjson writes them with the integral-float rewrite; None where
    orjson cannot write it or its text may not be ECMAScript's."""
    try:
        text = orjson.dumps(checked, option=orjson.OPT_SORT_KEYS)
    except TypeError:
        return None
    return None if _not_ecmascript(text) else _INTEGRAL.sub(b"", text)


def _holds_text(kind: FieldType) -> bool:
    if isinstance(kind, Scalar):
        return kind.kind == "string"
    if isinstance(kind, ArrayOf):
        return _holds_text(kind.item)
    return any(_holds_text(member) for member in kind.fields.values())


def record_topic(topic: str) -> str:
    """The topic as records hold it: ROS 1 bags may name topics without the leading ``/``,
    and a binding, a query or a dataset's description naming such a topic means the same."""
    return topic if topic.startswith("/") else f"/{topic}"


def recordable_topic(topic: str) -> bool:
    """Whether a record can hold ``topic``: a ROS name of at most 256 characters."""
    return TOPIC.fullmatch(record_topic(topic)) is not None


def check_envelope(record: Any) -> str:
    """Check a record's keys other than ``data``; return its template id."""
    if not isinstance(record, dict):
        raise RecordInvalid("", f"a record is an object, not {_kind_of(record)}")
    for key in record:
        if key not in RECORD_KEYS:
            shown = _shown(key) if isinstance(key, str) else repr(key)
            raise RecordInvalid(shown, "unknown key (template, topic, robot, t, data)")
    for key in RECORD_KEYS:
        if key not in record:
            raise RecordInvalid(key, "missing")
    template_id = record["template"]
    if not isinstance(template_id, str) or not TEMPLATE_ID.fullmatch(template_id):
        raise RecordInvalid("template", "must be a template id name@version")
    topic = record["topic"]
    if not isinstance(topic, str) or not TOPIC.fullmatch(topic):
        raise RecordInvalid("topic", "must be a ROS topic name starting with / (at most 256)")
    robot = record["robot"]
    if not isinstance(robot, str) or not _is_checksummed(robot):
        raise RecordInvalid("robot", "must be a checksummed address 0x...")
    t = record["t"]
    if isinstance(t, bool) or not isinstance(t, int) or not 0 <= t <= MAX_T:
        raise RecordInvalid("t", "must be an integer of nanoseconds from 0 to 2**63 - 1")
    return template_id


@lru_cache(maxsize=4096)
def _is_checksummed(address: str) -> bool:
    """EIP-55 costs a keccak; a batch or a bag repeats a few robots' addresses many times."""
    return len(address) == 42 and is_checksum_address(address)


def canonical_record(record: Mapping[str, Any]) -> bytes:
    """A record's canonical bytes, its Merkle leaf's data: RFC 8785 with ``t`` exact.

    ``t`` counts nanoseconds since the epoch (about 1.7e18 today), beyond the integers RFC 8785
    can hold, so integers are written with all their digits (see :func:`robocloud.jcs.canonical`).
    """
    return jcs.canonical(record, exact_integers=True)


def validate_record(template: Template, record: Any) -> None:
    """Check a whole record against ``template``; :class:`RecordInvalid` names the path."""
    template_id = check_envelope(record)
    if template_id != template.id:
        raise RecordInvalid("template", f"is {template_id}, expected {template.id}")
    validate_data(template, record["data"])
