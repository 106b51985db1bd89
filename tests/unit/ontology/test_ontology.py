"""The ontology, its shapes and its examples: they load, stay consistent under OWL 2 RL, and
every example conforms to its shapes while deliberately broken variants fail, each naming the
node, the path and what is wrong."""

from __future__ import annotations

from pathlib import Path

import owlrl
import pytest
from owlrl.Namespaces import ERRNS
from pyshacl import validate
from rdflib import OWL, RDF, SH, Graph, Namespace, URIRef
from rdflib.collection import Collection

from tests.procs import REPO

ONTOLOGY = REPO / "ontology"
EXAMPLES = sorted((ONTOLOGY / "examples").glob("*.ttl"))
RC = Namespace("https://w3id.org/robocloud#")
KINDS = {
    "application": RC.Application,
    "computation": RC.Computation,
    "configuration": RC.Configuration,
    "dataset": RC.Dataset,
    "file": RC.File,
    "result": RC.Result,
    "robot": RC.Robot,
    "sensor": RC.Sensor,
    "task": RC.Task,
    "template": RC.Template,
}
ROBOT = "did:pkh:eip155:1337:0x1a642f0E3c3aF545E7AcBD38b07251B3990914F1"
FILE = "ipfs://bafkreifhyd2reqnaxb6vmuv3gwnyum4osowzkclmxa2qdsj3fhkderxyem"
APP = "ipfs://bafkreia357kjlhicbaks5xy6g5ridjm6wevmf6ccufgzsdrlpfyi6ydb34"
JPEG = "https://www.iana.org/assignments/media-types/image/jpeg"
TASK = "ipfs://bafkreida5gq3v6rabjib2uiqzefbdra2cxrzx2sctf56h2igs73ndf2ouu"
DATASET = "ipfs://bafkreigadaazw2ulagvvq2gpjpunwmt2ove24azaevelt76nezy4jqvweq"
TEMPLATE = "ipfs://bafkreigyfykq6j7zji5odgbwfjasn6pbbpx5a4irvf74j62376sqyl3kbm"
JOB = "5c0e9a7d3b1f4e2a8c6d0b19"
INGESTION = f"{DATASET}#ingestion-{JOB}"


def load(path: Path) -> Graph:
    return Graph().parse(path, format="turtle")


@pytest.fixture(scope="module")
def ontology() -> Graph:
    return load(ONTOLOGY / "robocloud.ttl")


@pytest.fixture(scope="module")
def shapes() -> Graph:
    return load(ONTOLOGY / "shapes.ttl")


def closure(*graphs: Graph) -> Graph:
    merged = Graph()
    for graph in graphs:
        for triple in graph:
            merged.add(triple)
    owlrl.DeductiveClosure(owlrl.OWLRL_Semantics).expand(merged)
    return merged


def inconsistencies(graph: Graph) -> list[str]:
    """owl:Nothing members, owlrl's own inconsistency messages and shared disjoint members."""
    found = [f"{node} is an owl:Nothing" for node in graph.subjects(RDF.type, OWL.Nothing)]
    found += [str(message) for message in graph.objects(None, ERRNS.error)]
    pairs = list(graph.subject_objects(OWL.disjointWith))
    for group in graph.subjects(RDF.type, OWL.AllDisjointClasses):
        members = list(Collection(graph, next(graph.objects(group, OWL.members))))
        pairs += [(a, b) for i, a in enumerate(members) for b in members[i + 1 :]]
    for first, second in pairs:
        shared = set(graph.subjects(RDF.type, first)) & set(graph.subjects(RDF.type, second))
        found += [f"{node} is both {first} and {second}" for node in shared]
    return found


def violations(data: Graph, shapes: Graph) -> list[tuple[str, str, str]]:
    """(focus node, path, message) of each violation."""
    conforms, report, _ = validate(data, shacl_graph=shapes)
    assert isinstance(report, Graph)
    found = []
    for result in report.objects(None, SH.result):
        focus = report.value(result, SH.focusNode)
        path = report.value(result, SH.resultPath)
        message = report.value(result, SH.resultMessage)
        found.append((str(focus), str(path) if path is not None else "", str(message)))
    assert conforms == (not found)
    return sorted(found)


def test_the_ontology_loads_as_owl_with_every_class_labelled(ontology: Graph) -> None:
    assert (URIRef("https://w3id.org/robocloud"), RDF.type, OWL.Ontology) in ontology
    ours = [c for c in ontology.subjects(RDF.type, OWL.Class) if str(c).startswith(str(RC))]
    assert set(KINDS.values()) <= set(ours)
    for cls in ours:
        assert ontology.value(cls, URIRef("http://www.w3.org/2000/01/rdf-schema#label")), cls


def test_the_ontology_is_aligned_with_sosa_prov_and_dcat(ontology: Graph) -> None:
    sub = URIRef("http://www.w3.org/2000/01/rdf-schema#subClassOf")
    sosa = Namespace("http://www.w3.org/ns/sosa/")
    prov = Namespace("http://www.w3.org/ns/prov#")
    dcat = Namespace("http://www.w3.org/ns/dcat#")
    for child, parent in [
        (RC.Robot, sosa.Platform),
        (RC.Robot, prov.Agent),
        (RC.Sensor, sosa.Sensor),
        (RC.File, dcat.Distribution),
        (RC.Dataset, dcat.Dataset),
        (RC.Application, prov.Plan),
        (RC.Computation, prov.Activity),
        (RC.Ingestion, prov.Activity),
    ]:
        assert (child, sub, parent) in ontology


def test_there_is_one_example_of_each_kind() -> None:
    assert [path.stem for path in EXAMPLES] == sorted(KINDS)
    for path in EXAMPLES:
        graph = load(path)
        assert graph.value(predicate=RDF.type, object=KINDS[path.stem]) is not None, path


def test_the_owl_rl_closure_of_the_ontology_and_every_example_is_consistent(
    ontology: Graph,
) -> None:
    examples = [load(path) for path in EXAMPLES]
    closed = closure(ontology, *examples)
    assert inconsistencies(closed) == []
    # The closure did reason: the alignment types the examples' nodes.
    assert (URIRef(ROBOT), RDF.type, URIRef("http://www.w3.org/ns/sosa/Platform")) in closed
    assert (URIRef(FILE), RDF.type, URIRef("http://www.w3.org/ns/prov#Entity")) in closed


def test_a_file_that_is_also_a_robot_violates_disjointness(ontology: Graph) -> None:
    broken = load(ONTOLOGY / "examples" / "file.ttl")
    broken.add((URIRef(FILE), RDF.type, RC.Robot))
    found = inconsistencies(closure(ontology, broken))
    assert any("Robot" in line and "File" in line and FILE in line for line in found), found


def test_a_port_that_is_both_input_and_output_violates_disjointness(ontology: Graph) -> None:
    broken = load(ONTOLOGY / "examples" / "application.ttl")
    broken.add((URIRef(APP + "#input-image"), RDF.type, RC.OutputPort))
    found = inconsistencies(closure(ontology, broken))
    assert any(APP + "#input-image" in line for line in found), found


def test_a_sensor_mounted_on_a_file_is_inconsistent(ontology: Graph) -> None:
    """rc:mountedOn ranges over robots: reasoning makes the file a robot, which it cannot be."""
    broken = load(ONTOLOGY / "examples" / "sensor.ttl")
    broken += load(ONTOLOGY / "examples" / "file.ttl")
    broken.add((URIRef(ROBOT + "#sensor-camera_front"), RC.mountedOn, URIRef(FILE)))
    found = inconsistencies(closure(ontology, broken))
    assert any(FILE in line and "Robot" in line for line in found), found


def ingested_again(job: str, node: str, epoch: int, count: int) -> Graph:
    """The example dataset as a second job (on ``node``) describes it: its own ingestion."""
    text = (ONTOLOGY / "examples" / "dataset.ttl").read_text()
    for old, new in [
        (JOB, job),
        ("0x5050A4F4b3f9338C3472dcC01A87C76A144b3c9c", node),
        ("rc:epoch 42", f"rc:epoch {epoch}"),
        ("rc:recordCount 30000", f"rc:recordCount {count}"),
    ]:
        assert old in text, old
        text = text.replace(old, new)
    return Graph().parse(data=text, format="turtle")


def test_one_bag_ingested_by_two_jobs_and_two_nodes_still_conforms_and_is_consistent(
    ontology: Graph, shapes: Graph
) -> None:
    """The knowledge base holds every description in one graph: each ingestion's count, epoch
    and node stay on its own node, so the merged graph has one of each per ingestion (when they
    were on the dataset, two jobs gave it two counts and two epochs, a SHACL violation and no
    way to pair them)."""
    merged = load(ONTOLOGY / "examples" / "dataset.ttl")
    merged += ingested_again(
        "a1b2c3d4e5f60718293a4b5c", "0x5050A4F4b3f9338C3472dcC01A87C76A144b3c9c", 43, 7
    )
    merged += ingested_again(
        "0f1e2d3c4b5a69788796a5b4", "0x3325a78425F17a7E487Eb5666b2bFd93aBb06c70", 5, 30000
    )
    assert violations(merged, shapes) == []
    assert inconsistencies(closure(ontology, merged)) == []
    rows = merged.query(
        """PREFIX rc: <https://w3id.org/robocloud#>
        SELECT ?node ?epoch ?count WHERE {
            ?dataset rc:ingestion ?ingestion .
            ?ingestion rc:storageNode ?node ; rc:epoch ?epoch ; rc:recordCount ?count .
        } ORDER BY ?epoch"""
    )
    node = "did:pkh:eip155:1337:0x5050A4F4b3f9338C3472dcC01A87C76A144b3c9c"
    prover = "did:pkh:eip155:1337:0x3325a78425F17a7E487Eb5666b2bFd93aBb06c70"
    assert [(str(n), int(e), int(c)) for n, e, c in rows] == [  # type: ignore[misc]
        (prover, 5, 30000),
        (node, 42, 30000),
        (node, 43, 7),
    ]


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda path: path.stem)
def test_each_example_conforms_to_its_shapes(path: Path, shapes: Graph) -> None:
    assert violations(load(path), shapes) == []


def test_every_kind_has_a_node_shape(shapes: Graph) -> None:
    targeted = set(shapes.objects(None, SH.targetClass))
    assert set(KINDS.values()) <= targeted


def broken(name: str, old: str, new: str) -> Graph:
    text = (ONTOLOGY / "examples" / f"{name}.ttl").read_text()
    assert old in text, old
    return Graph().parse(data=text.replace(old, new), format="turtle")


BROKEN = [
    pytest.param(
        "robot",
        "rc:chainId 1337",
        "rc:chainId 1",
        [
            (
                ROBOT,
                "",
                f"the IRI {ROBOT} is not {ROBOT.replace('1337', '1')}",
            )
        ],
        id="robot-iri-disagrees-with-chain-id",
    ),
    pytest.param(
        "robot",
        '    rc:address "0x1a642f0E3c3aF545E7AcBD38b07251B3990914F1" ;\n',
        "",
        [(ROBOT, str(RC.address), "needs exactly one rc:address, 0x and 40 hex digits")],
        id="robot-without-address",
    ),
    pytest.param(
        "sensor",
        'rc:frame "camera_front_optical" ;',
        "",
        [
            (
                ROBOT + "#sensor-camera_front",
                str(RC.frame),
                "needs exactly one rc:frame, the coordinate frame it is mounted at",
            )
        ],
        id="sensor-without-frame",
    ),
    pytest.param(
        "file",
        "dcat:byteSize 10 ;",
        "dcat:byteSize -1 ;",
        [
            (
                FILE,
                "http://www.w3.org/ns/dcat#byteSize",
                "needs exactly one dcat:byteSize, a non-negative integer",
            )
        ],
        id="file-negative-size",
    ),
    pytest.param(
        "file",
        'rc:endTime "2026-03-01T10:00:00Z"',
        'rc:endTime "2026-03-01T09:00:00Z"',
        [(FILE, str(RC.startTime), "rc:startTime is one xsd:dateTime, not after rc:endTime")],
        id="file-ends-before-it-starts",
    ),
    pytest.param(
        "file",
        'rc:cid "bafkreifhyd2reqnaxb6vmuv3gwnyum4osowzkclmxa2qdsj3fhkderxyem"',
        'rc:cid "bafkreia357kjlhicbaks5xy6g5ridjm6wevmf6ccufgzsdrlpfyi6ydb34"',
        [
            (
                FILE,
                "",
                f"the IRI {FILE} is not ipfs:// followed by its rc:cid {APP[7:]}",
            )
        ],
        id="file-iri-is-not-its-cid",
    ),
    pytest.param(
        "file",
        "<https://www.iana.org/assignments/media-types/image/jpeg>",
        '"image/jpeg"',
        [
            (
                FILE,
                "http://www.w3.org/ns/dcat#mediaType",
                "needs exactly one dcat:mediaType, an IANA media type IRI",
            )
        ],
        id="file-media-type-as-text",
    ),
    pytest.param(
        "application",
        f"    rc:mediaType <{JPEG}> ;\n"
        f"    rc:requiresAttribute rc:width, rc:height .\n\n<{APP}#output-image>",
        f"    rc:requiresAttribute rc:width, rc:height .\n\n<{APP}#output-image>",
        [
            (
                APP + "#input-image",
                "",
                "a port takes or gives either one rc:mediaType or one rc:portTemplate",
            )
        ],
        id="input-port-without-type",
    ),
    pytest.param(
        "application",
        'a rc:InputPort ;\n    rc:name "image"',
        'a rc:InputPort ;\n    rc:name "picture"',
        [
            (
                APP + "#input-image",
                "",
                f"the IRI {APP}#input-image does not end in the name picture it declares",
            )
        ],
        id="port-name-disagrees-with-iri",
    ),
    pytest.param(
        "application",
        f"    rc:input <{APP}#input-image> ;\n",
        "",
        [(APP, str(RC.input), "needs at least one rc:input, an rc:InputPort described beside it")],
        id="application-without-input",
    ),
    pytest.param(
        "task",
        "rc:replication 3",
        "rc:replication 0",
        [
            (
                TASK,
                str(RC.replication),
                "needs exactly one rc:replication, a positive integer",
            )
        ],
        id="task-replication-zero",
    ),
    pytest.param(
        "computation",
        f"<{TASK}#computation> a",
        f"<{TASK}#run> a",
        [
            (
                TASK + "#run",
                "",
                f"the IRI {TASK}#run is not {TASK}#computation",
            )
        ],
        id="computation-named-apart-from-its-task",
    ),
    pytest.param(
        "dataset",
        'rc:tmtRoot "6e340b9cffb37a989ca544e6bb780a2c78901d3fb33738768511a30617afa01d"',
        'rc:tmtRoot "not-a-root"',
        [
            (
                INGESTION,
                str(RC.tmtRoot),
                "rc:tmtRoot is at most one SHA-256 root in 64 lowercase hex digits",
            )
        ],
        id="dataset-bad-tmt-root",
    ),
    pytest.param(
        "dataset",
        f'dcterms:identifier "{JOB}"',
        'dcterms:identifier "0123abcd"',
        [
            (
                INGESTION,
                "",
                f"the IRI {INGESTION} is not <dataset>#ingestion-<its dcterms:identifier> of a"
                " dataset naming it by rc:ingestion",
            )
        ],
        id="ingestion-named-apart-from-its-job",
    ),
    pytest.param(
        "dataset",
        f"    rc:ingestion <{INGESTION}> ;\n",
        "",
        [
            (
                DATASET,
                str(RC.ingestion),
                "needs at least one rc:ingestion, an rc:Ingestion described beside the dataset",
            ),
            (
                INGESTION,
                "",
                f"the IRI {INGESTION} is not <dataset>#ingestion-<its dcterms:identifier> of a"
                " dataset naming it by rc:ingestion",
            ),
        ],
        id="ingestion-no-dataset-names",
    ),
    pytest.param(
        "dataset",
        f"rc:records <{INGESTION}-records-imu-1>",
        f"rc:records <{DATASET}#ingestion-0123abcd-records-imu-1>",
        [
            (
                INGESTION,
                "",
                f"record count {DATASET}#ingestion-0123abcd-records-imu-1 is not named"
                f" {INGESTION}-records-<template name>-<version>",
            ),
            (
                INGESTION,
                str(RC.records),
                "rc:records names rc:RecordCount nodes described beside the ingestion",
            ),
        ],
        id="record-count-of-another-ingestion",
    ),
    pytest.param(
        "template",
        'dcterms:identifier "imu@1"',
        'dcterms:identifier "imu@2"',
        [
            (
                TEMPLATE,
                "",
                "dcterms:identifier imu@2 is not imu@1",
            )
        ],
        id="template-id-disagrees",
    ),
]


@pytest.mark.parametrize(("name", "old", "new", "expected"), BROKEN)
def test_a_broken_example_fails_naming_node_path_and_message(
    name: str, old: str, new: str, expected: list[tuple[str, str, str]], shapes: Graph
) -> None:
    assert violations(broken(name, old, new), shapes) == expected
