"""Semantic descriptions: what a robot, a file or an application is, in RDF a stranger understands.

A description is an RDF graph without blank nodes about one thing of a known kind (robot,
sensor, file, dataset, template, application, configuration, task, result, computation), in
the robocloud ontology (``ontology/robocloud.ttl``) and checked by its SHACL shapes
(``ontology/shapes.ttl``). What is stored, hashed and advertised is its canonical form: its
N-Triples lines sorted by code point, UTF-8, each ending in ``\\n``; its CID is the CID of those
bytes as ``robocloud.unixfs`` imports them (CIDv1 raw while they fit one chunk). Turtle and
RDF/XML are views of it.

Canonical documents are read by a strict parser of their own rather than rdflib's N-Triples
parser, for two reasons: rdflib normalises literals as it parses (``"...Z"^^xsd:dateTime``
becomes ``+00:00``), which would change the bytes and so the CID of what was read; and a
strict reader can name the line where a document stops being canonical.

Every document a stranger controls is bounded before it is parsed (bytes, and triples counted
as lines) so a description can never cost a service more than a small graph does.
"""

from __future__ import annotations

import mimetypes
import re
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from decimal import Decimal
from importlib import resources
from pathlib import PurePosixPath
from typing import Any, Final

from eth_utils.address import is_address, to_checksum_address
from rdflib import RDF, SH, XSD, BNode, Graph, Literal, Namespace, URIRef
from rdflib.term import Node

from robocloud.cid import CID, CIDError, parse_cid
from robocloud.errors import FormatError
from robocloud.unixfs import import_bytes

RC: Final = Namespace("https://w3id.org/robocloud#")
SOSA: Final = Namespace("http://www.w3.org/ns/sosa/")
PROV: Final = Namespace("http://www.w3.org/ns/prov#")
DCAT: Final = Namespace("http://www.w3.org/ns/dcat#")
DCTERMS: Final = Namespace("http://purl.org/dc/terms/")
RDFS: Final = Namespace("http://www.w3.org/2000/01/rdf-schema#")
MEDIA_TYPES: Final = "https://www.iana.org/assignments/media-types/"
PREFIXES: Final = {
    "rc": RC,
    "sosa": SOSA,
    "prov": PROV,
    "dcat": DCAT,
    "dcterms": DCTERMS,
    "rdfs": RDFS,
    "rdf": Namespace(str(RDF)),
    "xsd": Namespace(str(XSD)),
    "sh": Namespace(str(SH)),
}

MAX_DESCRIPTION_BYTES: Final = 1 << 20
"""A description is metadata: a megabyte is hundreds of times what the largest example needs."""
MAX_DESCRIPTION_TRIPLES: Final = 10_000
MAX_DESCRIBED_THINGS: Final = 100
"""Typed subjects in one description but record counts: every typed node is a SHACL target
(of its class, or of a superclass the description itself declares), and SHACL costs 5 to
25 ms per target whose shape runs SPARQL constraints (ports and ingestions too, not only the
kinds of description), so this bounds what validating a stranger's description costs (one
file beside 1,000 bare ``a rc:InputPort`` nodes took 10 s when only the kinds counted)."""
MAX_PROPERTY_VALUES: Final = 256
"""Values of one property of one node: ``sh:lessThanOrEquals`` compares every pair."""
MAX_RECORD_COUNTS: Final = MAX_PROPERTY_VALUES
"""Nodes typed ``rc:RecordCount`` only: their shape has core constraints alone (about 1 ms
each), and an ingestion names at most :data:`MAX_PROPERTY_VALUES` of them, one a template."""

KINDS: Final = {
    RC.Robot: "robot",
    RC.Sensor: "sensor",
    RC.File: "file",
    RC.Dataset: "dataset",
    RC.Template: "template",
    RC.Application: "application",
    RC.Configuration: "configuration",
    RC.Task: "task",
    RC.Result: "result",
    RC.Computation: "computation",
}
"""The classes a description may be about, and the kind each names."""

ATTRIBUTES: Final[dict[str, tuple[URIRef, type]]] = {
    "width": (RC.width, int),
    "height": (RC.height, int),
    "channels": (RC.channels, int),
    "encoding": (RC.encoding, str),
    "frame_rate": (RC.frameRate, Decimal),
    "duration": (RC.duration, Decimal),
}
"""Attributes a file carries and a port requires, by their Python name."""

NAME = re.compile(r"[a-z][a-z0-9_]{0,62}")
JOB_ID = re.compile(r"[0-9a-z]{1,64}")
MEDIA_TYPE = re.compile(r"[a-z]+/[A-Za-z0-9][A-Za-z0-9!#$&_.+-]*")
"""RFC 6838's restricted-name characters but ``^``, which no IRI may hold (N-Triples' and
SPARQL's IRIREF refuse it): a type with one could never be a description's, and its IRI broke
the query it went into, so it is refused as the parameter it came in."""
MCAP_MEDIA_TYPE: Final = "application/vnd.mcap"
"""IANA's type for MCAP files (registered in October 2026)."""
RECORDING_MEDIA_TYPES: Final[Mapping[str, str]] = {
    ".mcap": MCAP_MEDIA_TYPE,
    ".bag": "application/x-rosbag",
    ".db3": "application/vnd.sqlite3",
}
"""The recordings robots share, by file suffix: Python's ``mimetypes`` knows none of them, so
``robocloud describe`` refused a ROS bag until given ``--media-type``. ROS 1 bags have no
registered type; a ROS 2 storage file is an SQLite database (IANA's ``vnd.sqlite3``)."""
_IRI = r"<([^\x00-\x20<>\"{}|^`\\]*)>"
_LITERAL = r"\"((?:[^\"\\\n\r]|\\[\"\\nr])*)\"(?:@([a-z]+(?:-[a-z0-9]+)*)|\^\^" + _IRI + r")?"
_LINE = re.compile(f"{_IRI} {_IRI} (?:{_IRI}|{_LITERAL}) \\.")
_ABSOLUTE_IRI = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*:[^\x00-\x20<>\"{}|^`\\]*")
_UNESCAPE = {'\\"': '"', "\\\\": "\\", "\\n": "\n", "\\r": "\r"}


class SemanticError(FormatError):
    """A description breaks the wire format: robocloud.semantic's base error."""


class DescriptionSyntaxError(SemanticError):
    """The document is not RDF (``line`` counts from 1 where known)."""

    def __init__(self, message: str, line: int | None = None) -> None:
        super().__init__(message if line is None else f"line {line}: {message}")
        self.line = line


class NotADescriptionError(SemanticError):
    """Not a robocloud description: binary, blank nodes, not canonical, or no known kind."""


class DescriptionTooLargeError(SemanticError):
    """More bytes or triples than a description may hold; nothing of it was parsed."""

    def __init__(self, what: str, size: int, limit: int) -> None:
        super().__init__(f"the description has {size} {what}, more than the limit of {limit}")
        self.what = what
        self.size = size
        self.limit = limit


@dataclass(frozen=True)
class Violation:
    """One SHACL violation: the node it is about, the property path, and what is wrong."""

    focus: str
    path: str | None
    message: str
    value: str | None = None

    def __str__(self) -> str:
        where = self.focus if self.path is None else f"{self.focus} {self.path}"
        return f"{where}: {self.message}"

    def as_dict(self) -> dict[str, str | None]:
        return {
            "focus": self.focus,
            "path": self.path,
            "message": self.message,
            "value": self.value,
        }


class DescriptionInvalidError(SemanticError):
    """The description fails its shapes; ``violations`` lists each one."""

    def __init__(self, violations: Sequence[Violation]) -> None:
        lines = "; ".join(str(violation) for violation in violations)
        super().__init__(f"the description fails its shapes ({len(violations)}): {lines}")
        self.violations = list(violations)


@dataclass(frozen=True)
class Description:
    """An RDF graph without blank nodes, about things of the kinds in ``KINDS``.

    Build one with the ``*_description`` functions or read one with ``parse_canonical`` /
    ``parse_description``; it is not changed after that (its canonical bytes are cached).
    """

    graph: Graph
    _canonical: list[bytes] = field(default_factory=list, compare=False, repr=False)

    def canonical(self) -> bytes:
        """Sorted canonical N-Triples, UTF-8, each line ending in ``\\n``: what is stored."""
        if not self._canonical:
            self._canonical.append(canonical_ntriples(self.graph))
        return self._canonical[0]

    def cid(self) -> CID:
        """The CID of the canonical bytes, as cas computes it when they are added."""
        return import_bytes(self.canonical())[1]

    def turtle(self) -> str:
        return _with_prefixes(self.graph).serialize(format="turtle")

    def rdf_xml(self) -> str:
        return _with_prefixes(self.graph).serialize(format="xml")

    def subjects(self) -> dict[str, str]:
        """The described things: IRI -> kind (a result is a result, not also a file)."""
        found: dict[str, str] = {}
        for cls, kind in KINDS.items():
            for subject in self.graph.subjects(RDF.type, cls):
                if kind != "file" or str(subject) not in found:
                    found[str(subject)] = kind
        return found

    def __len__(self) -> int:
        return len(self.graph)


def _with_prefixes(graph: Graph) -> Graph:
    view = Graph()
    for prefix, namespace in PREFIXES.items():
        view.bind(prefix, namespace)
    for triple in graph:
        view.add(triple)
    return view


# ----- canonical N-Triples -----


def canonical_ntriples(graph: Graph) -> bytes:
    """The graph's canonical N-Triples; a blank node is refused (descriptions have none)."""
    lines = sorted({_term(s) + " " + _term(p) + " " + _term(o) + " .\n" for s, p, o in graph})
    return "".join(lines).encode("utf-8")


def _term(node: Node) -> str:
    if isinstance(node, URIRef):
        text = str(node)
        if not _ABSOLUTE_IRI.fullmatch(text):
            raise NotADescriptionError(f"{text[:200]!r} is not an absolute IRI")
        return f"<{text}>"
    if isinstance(node, Literal):
        lexical = (
            str(node)
            .replace("\\", "\\\\")
            .replace('"', '\\"')
            .replace("\n", "\\n")
            .replace("\r", "\\r")
        )
        if node.language:
            return f'"{lexical}"@{node.language.lower()}'
        if node.datatype is not None and node.datatype != XSD.string:
            return f'"{lexical}"^^{_term(node.datatype)}'
        return f'"{lexical}"'
    if isinstance(node, BNode):
        raise NotADescriptionError("a description has no blank nodes: name every node by IRI")
    raise NotADescriptionError(f"{node!r} is not an RDF term")


def parse_canonical(
    data: bytes,
    *,
    max_bytes: int = MAX_DESCRIPTION_BYTES,
    max_triples: int = MAX_DESCRIPTION_TRIPLES,
) -> Description:
    """Read a description in canonical form, exactly: any other bytes are refused.

    Raises ``DescriptionTooLargeError`` before parsing, ``NotADescriptionError`` for bytes
    that are not UTF-8 text, hold blank nodes, are out of canonical order or describe nothing
    of a known kind, and ``DescriptionSyntaxError`` naming the first line that is not a triple.
    """
    _check_size(data, max_bytes, max_triples)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise NotADescriptionError(
            f"a description is UTF-8 text; byte {exc.start} is not UTF-8"
        ) from None
    if "\x00" in text:
        raise NotADescriptionError("a description is text; this holds a NUL byte")
    if text and not text.endswith("\n"):
        raise DescriptionSyntaxError(
            "the last line does not end in a newline", text.count("\n") + 1
        )
    graph = Graph()
    previous = ""
    # Lines end in LF only: str.splitlines also splits at U+000B, U+0085, U+2028 and others,
    # which a literal may hold, and a description holding one read as a broken line.
    for number, bare in enumerate(text.split("\n")[:-1], start=1):
        line = bare + "\n"
        triple = _parse_line(bare, number)
        if line <= previous:
            order = (
                "repeats the previous line" if line == previous else "sorts before the one above"
            )
            raise NotADescriptionError(f"line {number} {order}: the document is not canonical")
        previous = line
        graph.add(triple)
    description = Description(graph)
    if description.canonical() != data:
        raise NotADescriptionError("the document is not in canonical N-Triples form")
    _require_subjects(description)
    return description


def _parse_line(line: str, number: int) -> tuple[URIRef, URIRef, URIRef | Literal]:
    match = _LINE.fullmatch(line)
    if match is None:
        if "_:" in line:
            raise NotADescriptionError(
                f"line {number} holds a blank node: a description names every node by IRI"
            )
        raise DescriptionSyntaxError(f"not a canonical N-Triples triple: {line[:200]!r}", number)
    subject, predicate, iri_object, lexical, language, datatype = match.groups()
    for iri in (subject, predicate, iri_object, datatype):
        if iri is not None and not _ABSOLUTE_IRI.fullmatch(iri):
            raise DescriptionSyntaxError(f"{iri[:200]!r} is not an absolute IRI", number)
    obj: URIRef | Literal
    if iri_object is not None:
        obj = URIRef(iri_object)
    else:
        value = re.sub(r"\\[\"\\nr]", lambda escape: _UNESCAPE[escape.group(0)], lexical)
        if datatype == str(XSD.string):
            raise NotADescriptionError(
                f"line {number}: canonical form writes xsd:string literals without a datatype"
            )
        obj = Literal(
            value,
            lang=language,
            datatype=URIRef(datatype) if datatype else None,
            normalize=False,
        )
    return URIRef(subject), URIRef(predicate), obj


def parse_description(
    data: bytes | str,
    rdf_format: str = "turtle",
    *,
    max_bytes: int = MAX_DESCRIPTION_BYTES,
    max_triples: int = MAX_DESCRIPTION_TRIPLES,
) -> Description:
    """Read a description written by hand or by another tool (Turtle, RDF/XML, N-Triples).

    Unlike ``parse_canonical`` any serialisation is accepted; its canonical form is computed.
    """
    raw = data.encode("utf-8") if isinstance(data, str) else data
    _check_size(raw, max_bytes, None)
    graph = Graph()
    try:
        graph.parse(data=raw, format=rdf_format)
    except Exception as exc:  # rdflib's parsers raise many unrelated types for bad input
        raise DescriptionSyntaxError(f"not {rdf_format}: {str(exc)[:500]}") from None
    if len(graph) > max_triples:
        raise DescriptionTooLargeError("triples", len(graph), max_triples)
    description = Description(graph)
    description.canonical()
    _require_subjects(description)
    return description


def _check_size(data: bytes, max_bytes: int, max_triples: int | None) -> None:
    if len(data) > max_bytes:
        raise DescriptionTooLargeError("bytes", len(data), max_bytes)
    if max_triples is not None:
        lines = data.count(b"\n")
        if lines > max_triples:
            raise DescriptionTooLargeError("triples", lines, max_triples)


def check_bounds(description: Description) -> None:
    """Refuse a description whose validation could cost more than a small one's."""
    types: dict[Node, set[Node]] = {}
    for subject, cls in description.graph.subject_objects(RDF.type):
        types.setdefault(subject, set()).add(cls)
    record_counts = sum(1 for classes in types.values() if RC.RecordCount in classes)
    things = sum(1 for classes in types.values() if classes != {RC.RecordCount})
    if things > MAX_DESCRIBED_THINGS:
        raise DescriptionTooLargeError("described things", things, MAX_DESCRIBED_THINGS)
    if record_counts > MAX_RECORD_COUNTS:
        raise DescriptionTooLargeError("record counts", record_counts, MAX_RECORD_COUNTS)
    counts: dict[tuple[Node, Node], int] = {}
    for subject, predicate, _ in description.graph:
        key = (subject, predicate)
        counts[key] = counts.get(key, 0) + 1
        if counts[key] > MAX_PROPERTY_VALUES:
            raise DescriptionTooLargeError(
                f"values of {_curie(predicate)} on {str(subject)[:200]}",
                len(list(description.graph.objects(subject, predicate))),
                MAX_PROPERTY_VALUES,
            )


def _require_subjects(description: Description) -> None:
    check_bounds(description)
    if not description.subjects():
        kinds = ", ".join(f"rc:{cls.removeprefix(str(RC))}" for cls in KINDS)
        raise NotADescriptionError(f"the document describes nothing of a known kind ({kinds})")


# ----- SHACL validation -----


_shapes_lock = threading.Lock()
_shapes: list[Graph] = []


def shapes() -> Graph:
    """The shapes graph, read once from the package's ``ontology/shapes.ttl``."""
    with _shapes_lock:
        if not _shapes:
            _shapes.append(Graph().parse(data=_ontology_file("shapes.ttl"), format="turtle"))
        return _shapes[0]


def ontology() -> Graph:
    return Graph().parse(data=_ontology_file("robocloud.ttl"), format="turtle")


def _ontology_file(name: str) -> str:
    return (resources.files("robocloud") / "ontology" / name).read_text(encoding="utf-8")


_NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")
"""Characters outside XML 1.0's ``Char`` production: no escape carries them (``&#x1;`` is not
well-formed either), so no RDF/XML view or SPARQL XML answer could hold them."""


def _not_xml(description: Description) -> set[Violation]:
    """A violation for each triple with a term XML 1.0 cannot carry.

    N-Triples and Turtle would carry a C0 control character in a literal, but the knowledge
    base also answers in RDF/XML and SPARQL XML results: one literal with U+0001 made every
    XML answer that included it ill-formed, which SPARQLWrapper and rdflib then refused.
    """
    found: set[Violation] = set()
    for subject, predicate, obj in description.graph:
        for term in (subject, predicate, obj, getattr(obj, "datatype", None)):
            bad = _NOT_XML.search(str(term)) if term is not None else None
            if bad is not None:
                path = _curie(predicate)
                message = (
                    f"{path} holds U+{ord(bad.group()):04X}, which XML 1.0 cannot carry "
                    "(descriptions are answered as RDF/XML and SPARQL XML results too)"
                )
                found.add(Violation(str(subject), path, message, str(obj)))
    return found


def violations(description: Description) -> list[Violation]:
    """Every SHACL violation of the description, and every term XML cannot carry, sorted by
    focus node, path and message.

    A value that breaks two constraints of one property shape (ill-typed and out of range)
    is listed once: the shape's message is the same for both.
    """
    from pyshacl import validate

    check_bounds(description)
    _, report, _ = validate(description.graph, shacl_graph=shapes(), allow_warnings=True)
    assert isinstance(report, Graph)
    found = _not_xml(description)
    for result in report.objects(None, SH.result):
        focus = report.value(result, SH.focusNode)
        path = report.value(result, SH.resultPath)
        message = report.value(result, SH.resultMessage)
        value = report.value(result, SH.value)
        found.add(
            Violation(
                focus=str(focus),
                path=_curie(path) if path is not None else None,
                message=str(message) if message is not None else "violates its shape",
                value=str(value) if value is not None and value != focus else None,
            )
        )
    return sorted(found, key=lambda v: (v.focus, v.path or "", v.message))


def validate(description: Description) -> Description:
    """The description itself when it conforms; ``DescriptionInvalidError`` otherwise."""
    found = violations(description)
    if found:
        raise DescriptionInvalidError(found)
    return description


def _curie(node: Node) -> str:
    """``rc:cid`` rather than the full IRI, where a known prefix covers it."""
    text = str(node)
    for prefix, namespace in PREFIXES.items():
        local = text.removeprefix(str(namespace))
        if local != text and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_-]*", local):
            return f"{prefix}:{local}"
    return text


# ----- names -----


def robot_iri(chain_id: int, address: str) -> str:
    """``did:pkh:eip155:<chain id>:<checksummed address>``."""
    if isinstance(chain_id, bool) or not isinstance(chain_id, int) or chain_id < 1:
        raise SemanticError(f"chain id {chain_id!r} is not a positive integer")
    return f"did:pkh:eip155:{chain_id}:{_address(address)}"


def sensor_iri(robot: str, name: str) -> str:
    return f"{_robot(robot)}#sensor-{_name(name, 'sensor name')}"


def content_iri(cid: CID | str) -> str:
    """``ipfs://<cid>`` (CIDv1, base32) for anything stored in cas."""
    return f"ipfs://{_cid(cid)}"


def computation_iri(task: CID | str) -> str:
    return f"{content_iri(task)}#computation"


def ingestion_iri(dataset: CID | str, job: str) -> str:
    """``<dataset>#ingestion-<job id>``: one per ingest job, so that each job's counts, epoch
    and storage node stay its own where two jobs or two nodes ingested one bag."""
    if not isinstance(job, str) or not JOB_ID.fullmatch(job):
        raise SemanticError(f"job id {str(job)[:100]!r} does not match [0-9a-z]{{1,64}}")
    return f"{content_iri(dataset)}#ingestion-{job}"


def guess_media_type(name: str) -> str | None:
    """The media type a file's name says, a recording's first (:data:`RECORDING_MEDIA_TYPES`),
    else Python's table, which also reads the host's ``mime.types``; None when neither knows."""
    suffix = PurePosixPath(name).suffix.lower()
    return RECORDING_MEDIA_TYPES.get(suffix) or mimetypes.guess_type(name, strict=False)[0]


def media_type_iri(media_type: str) -> str:
    """The IANA IRI of a media type (``image/jpeg``); an IRI already given is checked."""
    text = media_type.removeprefix(MEDIA_TYPES)
    if not MEDIA_TYPE.fullmatch(text):
        raise SemanticError(f"{media_type[:200]!r} is not a media type such as image/jpeg")
    return MEDIA_TYPES + text


def _address(address: str) -> str:
    if not isinstance(address, str) or not is_address(address):
        raise SemanticError(f"{str(address)[:100]!r} is not an Ethereum address")
    return str(to_checksum_address(address))


def _robot(robot: str) -> str:
    match = re.fullmatch(r"did:pkh:eip155:([1-9][0-9]*):(0x[0-9a-fA-F]{40})", robot)
    if match is None:
        raise SemanticError(f"{robot[:200]!r} is not a robot's did:pkh:eip155:<chain id>:<address>")
    return robot_iri(int(match.group(1)), match.group(2))


def _name(name: str, what: str) -> str:
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise SemanticError(f"{what} {str(name)[:100]!r} does not match [a-z][a-z0-9_]{{0,62}}")
    return name


def _cid(cid: CID | str) -> str:
    try:
        parsed = cid if isinstance(cid, CID) else parse_cid(cid, "cid")
    except CIDError as exc:
        raise SemanticError(str(exc)) from None
    return str(parsed.to_v1())


def _content(value: CID | str) -> URIRef:
    """A CID or ``ipfs://`` IRI as the content IRI."""
    text = str(value)
    return URIRef(content_iri(text.removeprefix("ipfs://")))


def _time(value: datetime, what: str) -> Literal:
    if value.tzinfo is None:
        raise SemanticError(f"{what} {value.isoformat()} has no time zone")
    return Literal(value)


def _count(value: int, what: str, minimum: int = 0) -> Literal:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise SemanticError(f"{what} {value!r} is not an integer of at least {minimum}")
    return Literal(value)


# ----- builders -----


class _Builder:
    """Collects the triples of one description."""

    def __init__(self) -> None:
        self.graph = Graph()

    def add(self, subject: str | URIRef, predicate: URIRef, obj: Node | str | None) -> None:
        if obj is None:
            return
        node = obj if isinstance(obj, Node) else Literal(obj)
        self.graph.add((URIRef(subject), predicate, node))

    def iris(self, subject: str | URIRef, predicate: URIRef, objects: Iterable[str]) -> None:
        for obj in objects:
            self.add(subject, predicate, URIRef(obj))

    def attributes(self, subject: str, values: Mapping[str, Any]) -> None:
        for name, value in values.items():
            if name not in ATTRIBUTES:
                raise SemanticError(
                    f"attribute {name!r} is not one of {', '.join(sorted(ATTRIBUTES))}"
                )
            predicate, kind = ATTRIBUTES[name]
            if kind is int:
                self.add(subject, predicate, _count(value, name, 1))
            elif kind is Decimal:
                if isinstance(value, bool) or not isinstance(value, int | float | Decimal):
                    raise SemanticError(f"attribute {name} {value!r} is not a number")
                self.add(subject, predicate, Literal(Decimal(str(value))))
            else:
                self.add(subject, predicate, Literal(str(value)))

    def time_range(self, subject: str, start: datetime | None, end: datetime | None) -> None:
        self.add(subject, RC.startTime, _time(start, "start") if start else None)
        self.add(subject, RC.endTime, _time(end, "end") if end else None)
        if start and end and start > end:
            raise SemanticError(f"start {start.isoformat()} is after end {end.isoformat()}")

    def done(self) -> Description:
        return Description(self.graph)


def robot_description(
    chain_id: int, address: str, *, label: str | None = None, sensors: Sequence[str] = ()
) -> Description:
    """A robot, named by its DID, with the names of the sensors it hosts."""
    iri = robot_iri(chain_id, address)
    build = _Builder()
    build.add(iri, RDF.type, RC.Robot)
    build.add(iri, RC.address, _address(address))
    build.add(iri, RC.chainId, Literal(chain_id))
    build.add(iri, RDFS.label, label)
    build.iris(iri, SOSA.hosts, [sensor_iri(iri, name) for name in sensors])
    return build.done()


def sensor_description(
    robot: str,
    name: str,
    frame: str,
    *,
    topics: Sequence[str] = (),
    observes: Sequence[str] = (),
    label: str | None = None,
) -> Description:
    """A sensor mounted on ``robot`` (its DID) at coordinate frame ``frame``."""
    iri = sensor_iri(robot, name)
    if not frame:
        raise SemanticError("a sensor's frame is not empty")
    build = _Builder()
    build.add(iri, RDF.type, RC.Sensor)
    build.add(iri, RC.name, name)
    build.add(iri, RC.mountedOn, URIRef(_robot(robot)))
    build.add(iri, RC.frame, frame)
    for topic in topics:
        build.add(iri, RC.topic, topic)
    build.iris(iri, SOSA.observes, observes)
    build.add(iri, RDFS.label, label)
    return build.done()


def _content_node(
    build: _Builder, cls: URIRef, cid: CID | str, media_type: str, byte_size: int
) -> str:
    iri = content_iri(cid)
    build.add(iri, RDF.type, cls)
    build.add(iri, RC.cid, _cid(cid))
    build.add(iri, DCAT.mediaType, URIRef(media_type_iri(media_type)))
    build.add(iri, DCAT.byteSize, _count(byte_size, "byte size"))
    return iri


def file_description(
    cid: CID | str,
    media_type: str,
    byte_size: int,
    *,
    title: str | None = None,
    producer: str | None = None,
    sensors: Sequence[str] = (),
    template: CID | str | None = None,
    start: datetime | None = None,
    end: datetime | None = None,
    attributes: Mapping[str, Any] | None = None,
) -> Description:
    """A file in cas: what it holds (media type, attributes such as width and height), who made it.

    ``producer`` is a robot's DID (``robot_iri``), ``sensors`` sensor IRIs (``sensor_iri``).
    """
    build = _Builder()
    iri = _content_node(build, RC.File, cid, media_type, byte_size)
    build.add(iri, DCTERMS.title, title)
    build.add(iri, RC.producedBy, URIRef(_robot(producer)) if producer else None)
    build.iris(iri, RC.sensor, sensors)
    build.add(iri, RC.template, _content(template) if template else None)
    build.time_range(iri, start, end)
    build.attributes(iri, attributes or {})
    return build.done()


@dataclass(frozen=True)
class TemplateCount:
    """How many records of one template version an ingestion made."""

    template_id: str
    template_cid: CID | str
    count: int


@dataclass(frozen=True)
class Ingestion:
    """One ingest job's records of a dataset, on the storage node that made and anchors them."""

    job: str
    """The job's id on its node; with the dataset's CID it names the ingestion."""
    storage_node: str
    start: datetime
    """The time of the first record, as ``end`` is of the last, over all its templates."""
    end: datetime
    record_counts: Sequence[TemplateCount]
    epoch: int | None = None
    """The node's first epoch holding every record; None while none is cut (or none will be:
    a node that does not anchor)."""
    tmt_root: str | None = None


def dataset_description(
    cid: CID | str,
    *,
    producer: str,
    ingestion: Ingestion,
    sensors: Sequence[str] = (),
    topics: Sequence[str] = (),
    files: Sequence[CID | str] = (),
    title: str | None = None,
) -> Description:
    """A bag (``cid``): its robot, sensors, topics and templates, and one ingestion of it.

    The ingestion's facts (counts, epoch, TMT root, storage node, time range) are on its own
    node, not on the dataset: a bag ingested by two jobs, or by two nodes, has two
    descriptions, and in the knowledge base's one graph facts on the dataset would merge into
    two counts and two epochs no query could pair."""
    iri = content_iri(cid)
    build = _Builder()
    build.add(iri, RDF.type, RC.Dataset)
    build.add(iri, RC.cid, _cid(cid))
    build.add(iri, DCTERMS.title, title)
    build.add(iri, RC.producedBy, URIRef(_robot(producer)))
    build.iris(iri, RC.sensor, sensors)
    for topic in topics:
        build.add(iri, RC.topic, topic)
    for entry in ingestion.record_counts:
        build.add(iri, RC.template, _content(entry.template_cid))
    for file in files:
        build.add(iri, DCAT.distribution, _content(file))
    node = ingestion_iri(cid, ingestion.job)
    build.add(iri, RC.ingestion, URIRef(node))
    _ingestion(build, node, ingestion)
    return build.done()


def _ingestion(build: _Builder, node: str, ingestion: Ingestion) -> None:
    build.add(node, RDF.type, RC.Ingestion)
    build.add(node, DCTERMS.identifier, ingestion.job)
    build.add(node, RC.storageNode, URIRef(_robot(ingestion.storage_node)))
    build.time_range(node, ingestion.start, ingestion.end)
    total = 0
    for entry in ingestion.record_counts:
        name, _, version = entry.template_id.partition("@")
        if not version.isdigit() or version.startswith("0"):
            raise SemanticError(f"template id {entry.template_id!r} is not name@version")
        counted = f"{node}-records-{_name(name, 'template name')}-{version}"
        build.add(node, RC.records, URIRef(counted))
        build.add(counted, RDF.type, RC.RecordCount)
        build.add(counted, RC.template, _content(entry.template_cid))
        build.add(counted, DCTERMS.identifier, entry.template_id)
        build.add(counted, RC.recordCount, _count(entry.count, "record count"))
        total += entry.count
    build.add(node, RC.recordCount, Literal(total))
    epoch = ingestion.epoch
    build.add(node, RC.epoch, _count(epoch, "epoch") if epoch is not None else None)
    tmt_root = ingestion.tmt_root
    if tmt_root is not None and not re.fullmatch(r"[0-9a-f]{64}", tmt_root):
        raise SemanticError(f"TMT root {tmt_root[:100]!r} is not 64 lowercase hex digits")
    build.add(node, RC.tmtRoot, tmt_root)


def template_description(
    cid: CID | str, name: str, version: int, *, description: str | None = None
) -> Description:
    """A record template version, named by the CID of its canonical JSON."""
    iri = content_iri(cid)
    _count(version, "template version", 1)
    build = _Builder()
    build.add(iri, RDF.type, RC.Template)
    build.add(iri, RC.cid, _cid(cid))
    build.add(iri, RC.name, _name(name, "template name"))
    build.add(iri, RC.version, str(version))
    build.add(iri, DCTERMS.identifier, f"{name}@{version}")
    build.add(iri, DCTERMS.description, description)
    return build.done()


@dataclass(frozen=True)
class Port:
    """An application's input or output: a media type or a record template, and the
    attributes its data must carry (``width``, ``height``, ...)."""

    name: str
    media_type: str | None = None
    template: CID | str | None = None
    attributes: Sequence[str] = ()


def application_description(
    cid: CID | str,
    name: str,
    version: str,
    *,
    inputs: Sequence[Port],
    outputs: Sequence[Port] = (),
    entrypoint: str | None = None,
    description: str | None = None,
) -> Description:
    """An application (its code's CID) with typed inputs and outputs."""
    iri = content_iri(cid)
    build = _Builder()
    build.add(iri, RDF.type, RC.Application)
    build.add(iri, RC.cid, _cid(cid))
    build.add(iri, RC.name, _name(name, "application name"))
    build.add(iri, RC.version, version)
    build.add(iri, RC.entrypoint, entrypoint)
    build.add(iri, DCTERMS.description, description)
    for direction, cls, predicate, ports in (
        ("input", RC.InputPort, RC.input, inputs),
        ("output", RC.OutputPort, RC.output, outputs),
    ):
        for port in ports:
            node = f"{iri}#{direction}-{_name(port.name, 'port name')}"
            if (port.media_type is None) == (port.template is None):
                raise SemanticError(f"port {port.name} has either a media type or a template")
            build.add(iri, predicate, URIRef(node))
            build.add(node, RDF.type, cls)
            build.add(node, RC.name, port.name)
            if port.media_type is not None:
                build.add(node, RC.mediaType, URIRef(media_type_iri(port.media_type)))
            if port.template is not None:
                build.add(node, RC.portTemplate, _content(port.template))
            for attribute in port.attributes:
                if attribute not in ATTRIBUTES:
                    raise SemanticError(
                        f"attribute {attribute!r} is not one of {', '.join(sorted(ATTRIBUTES))}"
                    )
                build.add(node, RC.requiresAttribute, ATTRIBUTES[attribute][0])
    return build.done()


def configuration_description(
    cid: CID | str, application: CID | str, media_type: str, byte_size: int
) -> Description:
    """A configuration document in cas for ``application``."""
    build = _Builder()
    iri = _content_node(build, RC.Configuration, cid, media_type, byte_size)
    build.add(iri, RC.configures, _content(application))
    return build.done()


def task_description(
    cid: CID | str,
    *,
    application: CID | str,
    inputs: Sequence[CID | str],
    requester: str,
    replication: int,
    configuration: CID | str | None = None,
    created: datetime | None = None,
) -> Description:
    """A task (its specification's CID): run ``application`` on ``inputs`` on several provers."""
    iri = content_iri(cid)
    build = _Builder()
    build.add(iri, RDF.type, RC.Task)
    build.add(iri, RC.cid, _cid(cid))
    build.add(iri, RC.application, _content(application))
    build.add(iri, RC.configuration, _content(configuration) if configuration else None)
    for item in inputs:
        build.add(iri, RC.taskInput, _content(item))
    build.add(iri, RC.requester, URIRef(_robot(requester)))
    build.add(iri, RC.replication, _count(replication, "replication", 1))
    build.add(iri, DCTERMS.created, _time(created, "created") if created else None)
    return build.done()


def result_description(
    cid: CID | str,
    *,
    task: CID | str,
    media_type: str,
    byte_size: int,
    attributes: Mapping[str, Any] | None = None,
) -> Description:
    """A task's accepted result, generated by the task's computation."""
    build = _Builder()
    iri = _content_node(build, RC.Result, cid, media_type, byte_size)
    build.add(iri, RC.resultOf, _content(task))
    build.add(iri, PROV.wasGeneratedBy, URIRef(computation_iri(str(task).removeprefix("ipfs://"))))
    build.attributes(iri, attributes or {})
    return build.done()


def computation_description(
    task: CID | str,
    *,
    application: CID | str,
    inputs: Sequence[CID | str],
    provers: Sequence[str],
    generated: Sequence[CID | str] = (),
    started: datetime | None = None,
    ended: datetime | None = None,
) -> Description:
    """The run of a task as a PROV activity: which application, which inputs, which provers."""
    iri = computation_iri(str(task).removeprefix("ipfs://"))
    build = _Builder()
    build.add(iri, RDF.type, RC.Computation)
    build.add(iri, RC.forTask, _content(task))
    build.add(iri, RC.application, _content(application))
    for item in inputs:
        build.add(iri, PROV.used, _content(item))
    build.iris(iri, RC.prover, [_robot(prover) for prover in provers])
    for item in generated:
        build.add(iri, PROV.generated, _content(item))
    build.add(iri, PROV.startedAtTime, _time(started, "started") if started else None)
    build.add(iri, PROV.endedAtTime, _time(ended, "ended") if ended else None)
    if started and ended and started > ended:
        raise SemanticError(f"started {started.isoformat()} is after ended {ended.isoformat()}")
    return build.done()
