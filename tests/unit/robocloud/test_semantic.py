"""robocloud.semantic: builders equal the ontology's examples, canonical form and CID, the
Turtle and RDF/XML views, SHACL validation with readable violations, and every malformed or
oversized document refused before it costs anything."""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime, timedelta, timezone

import pytest
from rdflib import RDF, Graph, Literal, URIRef

from robocloud import semantic
from robocloud.cid import CID, DAG_PB, RAW
from robocloud.semantic import (
    RC,
    Description,
    DescriptionInvalidError,
    DescriptionSyntaxError,
    DescriptionTooLargeError,
    Ingestion,
    NotADescriptionError,
    Port,
    SemanticError,
    TemplateCount,
    Violation,
)
from robocloud.unixfs import import_bytes
from tests.procs import REPO

EXAMPLES = REPO / "ontology" / "examples"
ADDRESS = "0x1a642f0E3c3aF545E7AcBD38b07251B3990914F1"
NODE = "0x5050A4F4b3f9338C3472dcC01A87C76A144b3c9c"
PROVER = "0x3325a78425F17a7E487Eb5666b2bFd93aBb06c70"
ROBOT = semantic.robot_iri(1337, ADDRESS)
CAMERA = semantic.sensor_iri(ROBOT, "camera_front")
IMU = semantic.sensor_iri(ROBOT, "imu")
BAG = "bafkreigadaazw2ulagvvq2gpjpunwmt2ove24azaevelt76nezy4jqvweq"
JPEG = "bafkreifhyd2reqnaxb6vmuv3gwnyum4osowzkclmxa2qdsj3fhkderxyem"
APP = "bafkreia357kjlhicbaks5xy6g5ridjm6wevmf6ccufgzsdrlpfyi6ydb34"
CONFIG = "bafkreicyps4ybl3w7xd6ki3j7ufz3etn74tgs5vw7cwgghrvr7wmjh7yz4"
TASK = "bafkreida5gq3v6rabjib2uiqzefbdra2cxrzx2sctf56h2igs73ndf2ouu"
RESULT = "bafkreidhfizs4zqkyoxf64w63iepb5a7ntywamlqe3khpqifviktk4ohi4"
IMU_TEMPLATE = "bafkreigyfykq6j7zji5odgbwfjasn6pbbpx5a4irvf74j62376sqyl3kbm"
T0 = datetime(2026, 3, 1, 10, 0, tzinfo=UTC)
JOB = "5c0e9a7d3b1f4e2a8c6d0b19"

BUILT: dict[str, Callable[[], Description]] = {
    "robot": lambda: semantic.robot_description(
        1337, ADDRESS.lower(), label="turtlebot-7", sensors=["camera_front", "imu"]
    ),
    "sensor": lambda: semantic.sensor_description(
        ROBOT,
        "camera_front",
        "camera_front_optical",
        topics=["/camera/front/image_raw"],
        observes=["https://w3id.org/robocloud#VisibleLight"],
        label="front RGB camera",
    ),
    "file": lambda: semantic.file_description(
        JPEG,
        "image/jpeg",
        10,
        title="camera.jpg",
        producer=ROBOT,
        sensors=[CAMERA],
        start=T0,
        end=T0,
        attributes={"width": 640, "height": 480, "channels": 3},
    ),
    "template": lambda: semantic.template_description(
        IMU_TEMPLATE,
        "imu",
        1,
        description="orientation, angular velocity and linear acceleration",
    ),
    "dataset": lambda: semantic.dataset_description(
        BAG,
        title="lab run 2026-03-01",
        producer=ROBOT,
        sensors=[CAMERA, IMU],
        topics=["/imu", "/camera/front/image_raw"],
        ingestion=Ingestion(
            JOB,
            semantic.robot_iri(1337, NODE),
            start=T0,
            end=T0 + timedelta(minutes=5),
            record_counts=[TemplateCount("imu@1", IMU_TEMPLATE, 30000)],
            epoch=42,
            tmt_root="6e340b9cffb37a989ca544e6bb780a2c78901d3fb33738768511a30617afa01d",
        ),
        files=[JPEG],
    ),
    "application": lambda: semantic.application_description(
        APP,
        "blur_faces",
        "1.2.0",
        entrypoint="python -m blur_faces",
        description="Blurs every face in a JPEG image; the output keeps the input's size.",
        inputs=[Port("image", media_type="image/jpeg", attributes=["width", "height"])],
        outputs=[Port("image", media_type="image/jpeg", attributes=["width", "height"])],
    ),
    "configuration": lambda: semantic.configuration_description(
        CONFIG, APP, "application/json", 11
    ),
    "task": lambda: semantic.task_description(
        TASK,
        application=APP,
        configuration=CONFIG,
        inputs=[JPEG],
        requester=ROBOT,
        replication=3,
        created=datetime(2026, 3, 1, 11, 0, tzinfo=UTC),
    ),
    "result": lambda: semantic.result_description(
        RESULT,
        task=TASK,
        media_type="image/jpeg",
        byte_size=10,
        attributes={"width": 640, "height": 480},
    ),
    "computation": lambda: semantic.computation_description(
        TASK,
        application=f"ipfs://{APP}",
        inputs=[JPEG, CONFIG],
        provers=[semantic.robot_iri(1337, NODE), semantic.robot_iri(1337, PROVER)],
        generated=[RESULT],
        started=datetime(2026, 3, 1, 11, 0, 5, tzinfo=UTC),
        ended=datetime(2026, 3, 1, 11, 0, 9, tzinfo=UTC),
    ),
}


def example(kind: str) -> Description:
    return semantic.parse_description((EXAMPLES / f"{kind}.ttl").read_bytes())


def test_there_is_a_builder_for_every_kind() -> None:
    assert sorted(BUILT) == sorted(semantic.KINDS.values())


@pytest.mark.parametrize("kind", sorted(BUILT))
def test_each_builder_gives_the_ontologys_example_and_it_validates(kind: str) -> None:
    built = BUILT[kind]()
    assert built.canonical() == example(kind).canonical()
    assert semantic.validate(built) is built
    assert kind in built.subjects().values()


def test_a_result_is_described_as_a_result_not_a_file() -> None:
    assert BUILT["result"]().subjects() == {f"ipfs://{RESULT}": "result"}


def test_canonical_form_is_sorted_escaped_utf8_ntriples_with_a_known_cid() -> None:
    graph = Graph()
    file = URIRef(f"ipfs://{JPEG}")
    graph.add((file, RDF.type, RC.File))
    graph.add((file, URIRef("http://purl.org/dc/terms/title"), Literal('a "b"\\c\nd\re é 字')))
    graph.add((file, URIRef("http://purl.org/dc/terms/title"), Literal("chat", lang="FR")))
    graph.add((file, RC.width, Literal(7)))
    canonical = Description(graph).canonical()
    assert (
        canonical
        == (
            f"<ipfs://{JPEG}> <http://purl.org/dc/terms/title> "
            '"a \\"b\\"\\\\c\\nd\\re é 字" .\n'
            f'<ipfs://{JPEG}> <http://purl.org/dc/terms/title> "chat"@fr .\n'
            f"<ipfs://{JPEG}> <http://www.w3.org/1999/02/22-rdf-syntax-ns#type> "
            "<https://w3id.org/robocloud#File> .\n"
            f'<ipfs://{JPEG}> <https://w3id.org/robocloud#width> "7"^^'
            "<http://www.w3.org/2001/XMLSchema#integer> .\n"
        ).encode()
    )
    description = semantic.parse_canonical(canonical)
    assert description.canonical() == canonical
    assert description.cid() == import_bytes(canonical)[1]
    assert description.cid().codec == RAW


@pytest.mark.parametrize("kind", sorted(BUILT))
def test_canonical_bytes_read_back_unchanged_with_the_same_cid(kind: str) -> None:
    built = BUILT[kind]()
    again = semantic.parse_canonical(built.canonical())
    assert again.canonical() == built.canonical()
    assert again.cid() == built.cid()
    lines = built.canonical().decode().splitlines(keepends=True)
    assert lines == sorted(lines)
    assert all(line.endswith(" .\n") for line in lines)


def test_a_description_larger_than_one_chunk_has_a_dag_pb_cid() -> None:
    graph = BUILT["file"]().graph
    for index in range(400):
        predicate = URIRef(f"https://example.org/note{index}")
        graph.add((URIRef(f"ipfs://{JPEG}"), predicate, Literal("x" * 1000)))
    description = Description(graph)
    assert len(description.canonical()) > 262144
    assert description.cid().codec == DAG_PB
    assert description.cid() == import_bytes(description.canonical())[1]
    assert semantic.parse_canonical(description.canonical()).cid() == description.cid()


@pytest.mark.parametrize("kind", sorted(BUILT))
def test_turtle_and_rdf_xml_are_views_of_the_same_description(kind: str) -> None:
    built = BUILT[kind]()
    turtle = built.turtle()
    assert "@prefix rc: <https://w3id.org/robocloud#> ." in turtle
    assert semantic.parse_description(turtle, "turtle").cid() == built.cid()
    xml = built.rdf_xml()
    assert xml.startswith("<?xml")
    assert semantic.parse_description(xml, "xml").cid() == built.cid()


def test_a_violation_names_focus_node_path_and_message() -> None:
    text = BUILT["file"]().canonical().replace(b'"640"', b'"-5"').replace(b'"480"', b'"x"')
    with pytest.raises(DescriptionInvalidError) as caught:
        semantic.validate(semantic.parse_canonical(text))
    focus = f"ipfs://{JPEG}"
    assert caught.value.violations == [
        Violation(focus, "rc:height", "rc:height is at most one positive integer", "x"),
        Violation(focus, "rc:width", "rc:width is at most one positive integer", "-5"),
    ]
    assert str(caught.value) == (
        "the description fails its shapes (2): "
        f"{focus} rc:height: rc:height is at most one positive integer; "
        f"{focus} rc:width: rc:width is at most one positive integer"
    )
    assert caught.value.violations[0].as_dict() == {
        "focus": focus,
        "path": "rc:height",
        "message": "rc:height is at most one positive integer",
        "value": "x",
    }


@pytest.mark.parametrize("character", ["\x01", "\x1f", "\x0b", "\ufffe"])
def test_a_literal_xml_cannot_carry_is_a_violation_naming_its_triple(character: str) -> None:
    """Canonical N-Triples carries a control character, but one in a literal made every XML
    answer that included it ill-formed (SPARQL XML results, RDF/XML)."""
    title = f"cam{character}era.jpg"
    text = BUILT["file"]().canonical().replace(b'"camera.jpg"', f'"{title}"'.encode())
    description = semantic.parse_canonical(text)
    with pytest.raises(DescriptionInvalidError) as caught:
        semantic.validate(description)
    message = (
        f"dcterms:title holds U+{ord(character):04X}, which XML 1.0 cannot carry "
        "(descriptions are answered as RDF/XML and SPARQL XML results too)"
    )
    assert caught.value.violations == [Violation(f"ipfs://{JPEG}", "dcterms:title", message, title)]


@pytest.mark.parametrize("title", ["a\tb\nc\rd", "\x7f\x85\u00e9", "line\u2028separator\u2029"])
def test_tabs_line_breaks_and_any_other_text_are_carried(title: str) -> None:
    """U+0085 and U+2028 are line breaks to ``str.splitlines`` only, not to N-Triples."""
    built = semantic.file_description(JPEG, media_type="image/jpeg", byte_size=10, title=title)
    read = semantic.parse_canonical(built.canonical())
    assert read.cid() == built.cid()
    assert semantic.violations(read) == []


def test_every_missing_required_property_is_listed() -> None:
    graph = Graph()
    graph.add((URIRef(f"ipfs://{APP}"), RDF.type, RC.Application))
    found = semantic.violations(Description(graph))
    assert [(v.path, v.message) for v in found] == [
        ("rc:cid", "needs exactly one rc:cid, a CIDv1 in base32 (b...)"),
        ("rc:input", "needs at least one rc:input, an rc:InputPort described beside it"),
        ("rc:name", "needs exactly one rc:name matching [a-z][a-z0-9_]{0,62}"),
        ("rc:version", "needs exactly one rc:version string"),
    ]


# ----- hostile documents -----

VALID = BUILT["file"]().canonical()


@pytest.mark.parametrize(
    ("document", "error", "message"),
    [
        pytest.param(b"\xff\xfe<a>", NotADescriptionError, "byte 0 is not UTF-8", id="binary"),
        pytest.param(b"<a> <b> \x00 .\n", NotADescriptionError, "NUL", id="nul"),
        pytest.param(b"", NotADescriptionError, "describes nothing", id="empty"),
        pytest.param(
            b'<http://xmlns.com/foaf/0.1/me> <http://xmlns.com/foaf/0.1/name> "x" .\n',
            NotADescriptionError,
            "describes nothing of a known kind",
            id="no-known-kind",
        ),
        pytest.param(
            b"_:b0 <http://www.w3.org/1999/02/22-rdf-syntax-ns#type> "
            b"<https://w3id.org/robocloud#File> .\n",
            NotADescriptionError,
            "line 1 holds a blank node",
            id="blank-node",
        ),
        pytest.param(
            b"".join(reversed(VALID.splitlines(keepends=True))),
            NotADescriptionError,
            "line 2 sorts before the one above",
            id="unsorted",
        ),
        pytest.param(
            VALID + VALID.splitlines(keepends=True)[-1],
            NotADescriptionError,
            "repeats the previous line",
            id="duplicate-line",
        ),
        pytest.param(VALID[:-1], DescriptionSyntaxError, "does not end in a newline", id="no-eol"),
        pytest.param(
            VALID.replace(b"> .\n", b">.\n", 1),
            DescriptionSyntaxError,
            "line 2: not a canonical N-Triples triple",
            id="syntax",
        ),
        pytest.param(
            VALID.replace(
                b'"camera.jpg"', b'"camera.jpg"^^<http://www.w3.org/2001/XMLSchema#string>'
            ),
            NotADescriptionError,
            "without a datatype",
            id="xsd-string-datatype",
        ),
        pytest.param(
            b"<relative> <http://b> <http://c> .\n",
            DescriptionSyntaxError,
            "'relative' is not an absolute IRI",
            id="relative-iri",
        ),
        pytest.param(
            VALID.replace(b'"camera.jpg"', b'"caf\\u00e9"'),
            DescriptionSyntaxError,
            "line 1",
            id="uchar-escape",
        ),
        pytest.param(b"<a> <b> <c> .\r\n", DescriptionSyntaxError, "line 1", id="crlf"),
    ],
)
def test_a_document_that_is_not_a_canonical_description_is_refused(
    document: bytes, error: type[SemanticError], message: str
) -> None:
    with pytest.raises(error, match=message):
        semantic.parse_canonical(document)


def test_a_document_over_the_byte_or_triple_bound_is_refused_before_parsing() -> None:
    with pytest.raises(DescriptionTooLargeError) as caught:
        semantic.parse_canonical(b"x" * 101, max_bytes=100)
    assert (caught.value.what, caught.value.size, caught.value.limit) == ("bytes", 101, 100)
    with pytest.raises(DescriptionTooLargeError, match="9 triples, more than the limit of 8"):
        semantic.parse_canonical(b"garbage\n" * 9, max_triples=8)
    with pytest.raises(DescriptionTooLargeError, match="bytes"):
        semantic.parse_description("@prefix x: <http://x#> .\n" * 100, max_bytes=1000)
    turtle = "\n".join(f"<ipfs://{JPEG}> <http://x/{i}> {i} ." for i in range(20))
    with pytest.raises(DescriptionTooLargeError, match="20 triples, more than the limit of 10"):
        semantic.parse_description(turtle, max_triples=10)


def test_too_many_described_things_or_values_of_one_property_are_refused() -> None:
    files = Graph()
    for index in range(semantic.MAX_DESCRIBED_THINGS + 1):
        files += semantic.file_description(
            CID.from_block(str(index).encode()), "image/png", 1
        ).graph
    crowded = Description(files)
    message = "101 described things, more than the limit of 100"
    with pytest.raises(DescriptionTooLargeError, match=message):
        semantic.violations(crowded)
    with pytest.raises(DescriptionTooLargeError, match=message):
        semantic.parse_canonical(crowded.canonical())
    graph = BUILT["file"]().graph
    for index in range(semantic.MAX_PROPERTY_VALUES + 1):
        graph.add((URIRef(f"ipfs://{JPEG}"), RC.sensor, URIRef(f"{CAMERA}{index}")))
    with pytest.raises(DescriptionTooLargeError, match="258 values of rc:sensor on ipfs://"):
        semantic.parse_canonical(Description(graph).canonical())
    with pytest.raises(DescriptionTooLargeError, match="limit of 256"):
        semantic.validate(Description(graph))


@pytest.mark.parametrize("cls", [RC.InputPort, RC.Ingestion, RC.Sensor])
def test_typed_nodes_of_any_class_count_as_described_things(cls: URIRef) -> None:
    """Each typed node is a SHACL target: a port or an ingestion costs 10 to 25 ms of SPARQL
    constraints, so one file described beside 1,000 bare ``a rc:InputPort`` nodes took 10 s to
    validate (9,000 within the triple bound, 90 s) when only the kinds of description were
    counted. It is refused before validation now."""
    graph = BUILT["file"]().graph
    for index in range(semantic.MAX_DESCRIBED_THINGS):
        graph.add((URIRef(f"ipfs://{BAG}#part-{index}"), RDF.type, cls))
    crowded = Description(graph)
    message = "101 described things, more than the limit of 100"
    with pytest.raises(DescriptionTooLargeError, match=message):
        semantic.parse_canonical(crowded.canonical())
    with pytest.raises(DescriptionTooLargeError, match=message):
        semantic.violations(crowded)


def test_a_node_typed_by_a_class_declared_in_the_description_counts_too() -> None:
    """SHACL's targets include instances of subclasses the data graph declares."""
    graph = BUILT["file"]().graph
    sub = URIRef("https://example.org/Sub")
    graph.add((sub, URIRef("http://www.w3.org/2000/01/rdf-schema#subClassOf"), RC.RecordCount))
    for index in range(semantic.MAX_DESCRIBED_THINGS):
        graph.add((URIRef(f"ipfs://{BAG}#part-{index}"), RDF.type, sub))
    with pytest.raises(DescriptionTooLargeError, match="101 described things"):
        semantic.parse_canonical(Description(graph).canonical())


def test_a_dataset_of_as_many_templates_as_a_property_may_name_fits() -> None:
    """Record counts have a bound of their own: their shape runs no SPARQL (about 1 ms each)."""
    counts = [
        TemplateCount(f"t{index}@1", IMU_TEMPLATE, index)
        for index in range(semantic.MAX_PROPERTY_VALUES)
    ]
    built = semantic.dataset_description(
        BAG, producer=ROBOT, ingestion=Ingestion(JOB, ROBOT, T0, T0, counts)
    )
    assert semantic.violations(semantic.parse_canonical(built.canonical())) == []
    graph = built.graph
    graph.add((URIRef(f"ipfs://{BAG}#ingestion-{JOB}-records-extra-1"), RDF.type, RC.RecordCount))
    with pytest.raises(DescriptionTooLargeError, match="257 record counts, more than the limit"):
        semantic.parse_canonical(Description(graph).canonical())


def test_a_document_that_is_not_rdf_is_a_syntax_error() -> None:
    with pytest.raises(DescriptionSyntaxError, match="not turtle"):
        semantic.parse_description("<a> <b> ")
    with pytest.raises(DescriptionSyntaxError, match="not xml"):
        semantic.parse_description("<rdf:RDF", "xml")
    with pytest.raises(NotADescriptionError, match="blank nodes"):
        semantic.parse_description(f"[] a <{RC.File}> .")


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: semantic.robot_iri(0, ADDRESS), "chain id 0"),
        (lambda: semantic.robot_iri(1, "0x1234"), "'0x1234' is not an Ethereum address"),
        (lambda: semantic.sensor_iri(ROBOT, "Front Camera"), "sensor name 'Front Camera'"),
        (lambda: semantic.sensor_iri("did:web:x", "cam"), "'did:web:x' is not a robot's did"),
        (lambda: semantic.content_iri("Qm-not-a-cid"), "Qm-not-a-cid"),
        (lambda: semantic.media_type_iri("jpeg"), "'jpeg' is not a media type"),
        (
            lambda: semantic.file_description(JPEG, "image/jpeg", -1),
            "byte size -1 is not an integer of at least 0",
        ),
        (
            lambda: semantic.file_description(JPEG, "image/jpeg", 1, attributes={"depth": 3}),
            "attribute 'depth' is not one of",
        ),
        (
            lambda: semantic.file_description(
                JPEG,
                "image/jpeg",
                1,
                start=datetime(2026, 1, 1),
            ),
            "has no time zone",
        ),
        (
            lambda: semantic.file_description(
                JPEG, "image/jpeg", 1, start=T0, end=T0 - timedelta(seconds=1)
            ),
            "is after end",
        ),
        (
            lambda: semantic.application_description(
                APP, "app", "1", inputs=[Port("x", media_type="image/png", template=IMU_TEMPLATE)]
            ),
            "either a media type or a template",
        ),
        (
            lambda: semantic.dataset_description(
                BAG,
                producer=ROBOT,
                ingestion=Ingestion(
                    JOB, ROBOT, T0, T0, record_counts=[TemplateCount("imu", IMU_TEMPLATE, 1)]
                ),
            ),
            "'imu' is not name@version",
        ),
        (
            lambda: semantic.dataset_description(
                BAG, producer=ROBOT, ingestion=Ingestion(JOB, ROBOT, T0, T0, [], tmt_root="AB")
            ),
            "TMT root 'AB'",
        ),
        (
            lambda: semantic.dataset_description(
                BAG, producer=ROBOT, ingestion=Ingestion("Job 1", ROBOT, T0, T0, [])
            ),
            "job id 'Job 1' does not match",
        ),
    ],
)
def test_a_builder_refuses_what_would_not_be_a_valid_description(
    build: Callable[[], object], message: str
) -> None:
    with pytest.raises(SemanticError, match=message):
        build()


def test_times_in_other_zones_are_kept_as_written() -> None:
    start = datetime(2026, 3, 1, 12, 0, tzinfo=timezone(timedelta(hours=2)))
    description = semantic.file_description(JPEG, "image/jpeg", 1, start=start, end=start)
    assert b'"2026-03-01T12:00:00+02:00"^^<http://www.w3.org/2001/XMLSchema#dateTime>' in (
        description.canonical()
    )
    semantic.validate(description)


@pytest.mark.parametrize(
    ("name", "media_type"),
    [
        ("run.mcap", "application/vnd.mcap"),
        ("RUN.MCAP", "application/vnd.mcap"),
        ("2014-07-21-12-42-53.bag", "application/x-rosbag"),
        ("rosbag2_0.db3", "application/vnd.sqlite3"),
        ("front.png", "image/png"),
        ("notes.unknownext", None),
        ("bag", None),
    ],
)
def test_guess_media_type_knows_recordings_before_the_platform_table(
    name: str, media_type: str | None
) -> None:
    assert semantic.guess_media_type(name) == media_type
    if media_type is not None:
        semantic.media_type_iri(media_type)
