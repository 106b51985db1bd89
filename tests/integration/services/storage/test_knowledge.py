"""The knowledge base as robots use it: descriptions added by CID, SPARQL through real SPARQL
clients (SPARQLWrapper, rdflib's SPARQLStore) unchanged, application discovery, and every bad
input answered with what is wrong while nothing is stored.

One cas and one storage service (anchoring and the ledger follower off) serve the module.
"""

from __future__ import annotations

import csv
import http.server
import io
import threading
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from rdflib import RDF, Graph, Literal, URIRef
from rdflib.plugins.stores.sparqlstore import SPARQLStore
from SPARQLWrapper import CSV, JSON, POST, TURTLE, XML, SPARQLWrapper

from robocloud import semantic
from robocloud.cas import Cas
from robocloud.errors import ApiError
from robocloud.identity import Identity
from robocloud.knowledge import Knowledge
from robocloud.semantic import Description
from robocloud.unixfs import ImportParams
from tests.flood import flooding
from tests.procs import REPO, ServiceProcess
from tests.waiting import wait_for

EXAMPLES = REPO / "ontology" / "examples"
RC = "https://w3id.org/robocloud#"
JPEG_FILE = "ipfs://bafkreifhyd2reqnaxb6vmuv3gwnyum4osowzkclmxa2qdsj3fhkderxyem"
ROBOT_ADDRESS = "0x1a642f0E3c3aF545E7AcBD38b07251B3990914F1"
APP = "ipfs://bafkreia357kjlhicbaks5xy6g5ridjm6wevmf6ccufgzsdrlpfyi6ydb34"
PREFIX = f"PREFIX rc: <{RC}>\n"
TIMEOUT_S = 4
MAX_RESULT_BYTES = 64 * 1024


class Services:
    def __init__(self, cas: ServiceProcess, storage: ServiceProcess, identity: Identity) -> None:
        self.cas_process = cas
        self.storage = storage
        self.identity = identity
        self.sparql = f"{storage.url}/v1/knowledge/sparql"

    def cas(self) -> Cas:
        return Cas(self.cas_process.url, self.identity)

    def knowledge(self) -> Knowledge:
        return Knowledge(self.storage.url, self.identity)

    def put(self, data: bytes) -> str:
        with self.cas() as cas:
            return str(cas.add_bytes(data))

    def post(self, cid: str) -> httpx.Response:
        with self.knowledge() as knowledge:
            return knowledge.send("POST", "/v1/knowledge", json={"cid": cid})

    def state(self) -> dict[str, Any]:
        return dict(httpx.get(f"{self.storage.url}/v1/knowledge", timeout=10).json())

    def stored(self) -> set[str]:
        directory = self.storage.data_dir / "knowledge" / "descriptions"
        return {path.stem for path in directory.glob("*.nt")}


@pytest.fixture(scope="module")
def services(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Services]:
    root = tmp_path_factory.mktemp("knowledge")
    with (
        ServiceProcess("cas", root / "cas") as cas,
        ServiceProcess(
            "storage",
            root / "storage",
            {
                "ROBOCLOUD_CAS_URL": cas.url,
                "ROBOCLOUD_STORAGE_ANCHOR": "false",
                "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
                "ROBOCLOUD_KNOWLEDGE_QUERY_TIMEOUT_S": str(TIMEOUT_S),
                "ROBOCLOUD_KNOWLEDGE_MAX_QUERY_BYTES": "4096",
                "ROBOCLOUD_KNOWLEDGE_MAX_RESULT_BYTES": str(MAX_RESULT_BYTES),
            },
        ) as storage,
    ):
        services = Services(cas, storage, Identity.generate())
        with services.cas() as cas_client, services.knowledge() as knowledge:
            for path in sorted(EXAMPLES.glob("*.ttl")):
                knowledge.store(semantic.parse_description(path.read_bytes()), cas_client)
        yield services


def example(kind: str) -> Description:
    return semantic.parse_description((EXAMPLES / f"{kind}.ttl").read_bytes())


def error(response: httpx.Response, status: int, code: str) -> dict[str, Any]:
    assert response.status_code == status, response.text
    body = response.json()["error"]
    assert body["code"] == code, body
    return dict(body["details"])


# ----- adding descriptions -----


def test_every_example_is_indexed_once_and_adding_again_changes_nothing(
    services: Services,
) -> None:
    cids = {str(example(path.stem).cid()) for path in EXAMPLES.glob("*.ttl")}
    assert services.stored() == cids
    assert services.state()["descriptions"] == len(cids)
    again = services.post(str(example("file").cid()))
    assert again.status_code == 200
    assert again.json() == {
        "cid": str(example("file").cid()),
        "subjects": {JPEG_FILE: "file"},
        "triples": 12,
        "new": False,
    }
    assert services.state()["descriptions"] == len(cids)


def unchanged(services: Services, before: set[str]) -> None:
    assert services.stored() == before
    assert services.state()["descriptions"] == len(before)


def test_a_description_failing_its_shapes_is_refused_listing_each_violation(
    services: Services,
) -> None:
    before = services.stored()
    broken = example("file").canonical().replace(b'"640"', b'"-1"').replace(b'"3"^^', b'"0"^^')
    cid = services.put(semantic.parse_canonical(broken).canonical())
    details = error(services.post(cid), 400, "description_invalid")
    assert details == {
        "cid": cid,
        "violations": [
            {
                "focus": JPEG_FILE,
                "path": "rc:channels",
                "message": "rc:channels is at most one positive integer",
                "value": "0",
            },
            {
                "focus": JPEG_FILE,
                "path": "rc:width",
                "message": "rc:width is at most one positive integer",
                "value": "-1",
            },
        ],
    }
    unchanged(services, before)


def test_a_literal_xml_cannot_carry_is_refused_naming_its_triple(services: Services) -> None:
    """One was accepted, and from then on every XML answer holding it (SPARQL XML results,
    a CONSTRUCT as RDF/XML) was ill-formed: SPARQLWrapper and rdflib could not read them."""
    before = services.stored()
    text = example("file").canonical().replace(b'"camera.jpg"', b'"cam\x01era.jpg"')
    cid = services.put(semantic.parse_canonical(text).canonical())
    details = error(services.post(cid), 400, "description_invalid")
    assert details == {
        "cid": cid,
        "violations": [
            {
                "focus": JPEG_FILE,
                "path": "dcterms:title",
                "message": "dcterms:title holds U+0001, which XML 1.0 cannot carry "
                "(descriptions are answered as RDF/XML and SPARQL XML results too)",
                "value": "cam\x01era.jpg",
            }
        ],
    }
    unchanged(services, before)


@pytest.mark.parametrize(
    ("document", "code", "details"),
    [
        pytest.param(b"<a> <b> .\n", "rdf_unparsable", {"line": 1}, id="unparsable"),
        pytest.param(b"\xff\xd8\xff\xe0JFIF\x00", "not_a_description", {}, id="jpeg-bytes"),
        pytest.param(
            b'<http://xmlns.com/foaf/0.1/me> <http://xmlns.com/foaf/0.1/name> "robot" .\n',
            "not_a_description",
            {},
            id="rdf-of-no-known-kind",
        ),
        pytest.param(
            f"{example('file').turtle()}".encode(), "rdf_unparsable", {"line": 1}, id="turtle"
        ),
        pytest.param(
            b"x" * (semantic.MAX_DESCRIPTION_BYTES + 1),
            "description_too_large",
            {"limit": semantic.MAX_DESCRIPTION_BYTES},
            id="too-large",
        ),
    ],
)
def test_bytes_that_are_not_a_canonical_description_are_refused(
    services: Services, document: bytes, code: str, details: dict[str, Any]
) -> None:
    before = services.stored()
    cid = services.put(document)
    assert error(services.post(cid), 400, code) == {"cid": cid, **details}
    unchanged(services, before)


def test_a_description_padded_with_bare_typed_nodes_is_refused_before_validation(
    services: Services,
) -> None:
    """1,000 bare ``a rc:InputPort`` nodes beside a file: SHACL spent 10 s of the node's
    CPU on them (90 s at the line bound) while only the kinds of description were counted."""
    before = services.stored()
    graph = example("file").graph
    for index in range(1000):
        graph.add((URIRef(f"{JPEG_FILE}#input-p{index}"), RDF.type, URIRef(f"{RC}InputPort")))
    cid = services.put(Description(graph).canonical())
    # Too large, not invalid: refused before SHACL, which would have named 2,000 violations.
    details = error(services.post(cid), 400, "description_too_large")
    assert details == {"cid": cid, "limit": semantic.MAX_DESCRIBED_THINGS}
    unchanged(services, before)


def test_a_cid_cas_does_not_have_or_that_is_malformed_is_named(services: Services) -> None:
    before = services.stored()
    missing = str(semantic.Description(Graph()).cid())
    assert error(services.post(missing), 404, "description_not_found") == {"cid": missing}
    assert error(services.post("bafy-not-a-cid"), 400, "invalid_cid")["cid"] == "bafy-not-a-cid"
    unsigned = httpx.post(
        f"{services.storage.url}/v1/knowledge", json={"cid": str(example("file").cid())}
    )
    assert unsigned.status_code == 401
    with services.knowledge() as knowledge:
        surrogate = knowledge.send(
            "POST",
            "/v1/knowledge",
            content=b'{"cid": "bafk\\ud800"}',
            headers={"Content-Type": "application/json"},
        )
    assert error(surrogate, 400, "invalid_json") == {}
    unchanged(services, before)


def test_a_description_under_another_cid_than_its_canonical_one_is_refused(
    services: Services,
) -> None:
    """The same bytes under a CIDv0 (dag-pb) were acknowledged, new: true, then never loaded
    by the SPARQL workers, which check each file's bytes against its name."""
    before = services.stored()
    robot = Identity.generate().address
    text = example("robot").canonical().decode().replace(ROBOT_ADDRESS, robot)
    data = semantic.parse_description(text, "nt").canonical()
    with services.cas() as cas:
        v0 = str(cas.add_bytes(data, params=ImportParams(cid_version=0, raw_leaves=False)))
        v1_dag_pb = str(cas.add_bytes(data, params=ImportParams(raw_leaves=False)))
    canonical = str(semantic.parse_canonical(data).cid())
    assert v0.startswith("Qm")
    assert v1_dag_pb.startswith("bafybei")
    for cid in (v0, v1_dag_pb):
        details = error(services.post(cid), 400, "cid_not_canonical")
        assert details == {"cid": cid, "expected": canonical}
    unchanged(services, before)


# ----- SPARQL through real clients -----

FILES_QUERY = PREFIX + "SELECT ?file ?width WHERE { ?file a rc:File ; rc:width ?width }"


def test_sparqlwrapper_reads_json_xml_and_csv_by_get_and_post(services: Services) -> None:
    for method in ("GET", POST):
        client = SPARQLWrapper(services.sparql)
        client.setMethod(method)
        client.setQuery(FILES_QUERY)
        client.setReturnFormat(JSON)
        rows = client.queryAndConvert()["results"]["bindings"]
        assert [(row["file"]["value"], row["width"]["value"]) for row in rows] == [
            (JPEG_FILE, "640")
        ]
        client.setReturnFormat(XML)
        document = client.queryAndConvert()
        results = document.getElementsByTagName("uri")
        assert [node.firstChild.data for node in results] == [JPEG_FILE]
        client.setReturnFormat(CSV)
        table = list(csv.reader(io.StringIO(client.queryAndConvert().decode())))
        assert table == [["file", "width"], [JPEG_FILE, "640"]]


def test_sparqlwrapper_reads_a_construct_as_turtle(services: Services) -> None:
    client = SPARQLWrapper(services.sparql)
    client.setQuery(
        PREFIX + "CONSTRUCT { ?app rc:name ?name } WHERE { ?app rc:name ?name ; a rc:Application }"
    )
    client.setReturnFormat(TURTLE)
    graph = Graph().parse(data=client.queryAndConvert(), format="turtle")
    assert set(graph) == {(URIRef(APP), URIRef(RC + "name"), Literal("blur_faces"))}


def test_rdflib_sparqlstore_queries_the_knowledge_base_unchanged(services: Services) -> None:
    store = SPARQLStore(query_endpoint=services.sparql)
    graph = Graph(store=store)
    rows = list(graph.query(FILES_QUERY))
    assert [(str(row[0]), int(row[1])) for row in rows] == [(JPEG_FILE, 640)]
    assert graph.query(PREFIX + f"ASK {{ <{APP}> a rc:Application }}").askAnswer is True
    triples = set(graph.triples((URIRef(APP), URIRef(RC + "name"), None)))
    assert triples == {(URIRef(APP), URIRef(RC + "name"), Literal("blur_faces"))}


@pytest.mark.parametrize(
    ("accept", "media"),
    [
        (None, "application/sparql-results+json"),
        ("*/*", "application/sparql-results+json"),
        ("text/csv", "text/csv"),
        ("application/sparql-results+xml;q=0.9, text/csv;q=0.1", "application/sparql-results+xml"),
        ("text/*", "text/csv"),
    ],
)
def test_select_answers_by_content_negotiation(
    services: Services, accept: str | None, media: str
) -> None:
    headers = {"Accept": accept} if accept else {}
    answer = httpx.get(services.sparql, params={"query": FILES_QUERY}, headers=headers)
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-type"].split(";")[0] == media
    assert JPEG_FILE in answer.text


def test_construct_answers_turtle_n_triples_or_rdf_xml(services: Services) -> None:
    query = PREFIX + f"CONSTRUCT {{ <{APP}> ?p ?o }} WHERE {{ <{APP}> ?p ?o }}"
    expected = {t for t in example("application").graph if str(t[0]) == APP}
    for accept, rdf_format in [
        ("text/turtle", "turtle"),
        ("application/n-triples", "nt"),
        ("application/rdf+xml", "xml"),
    ]:
        answer = httpx.get(services.sparql, params={"query": query}, headers={"Accept": accept})
        assert answer.headers["content-type"].startswith(accept)
        assert set(Graph().parse(data=answer.content, format=rdf_format)) == expected


def test_an_unacceptable_format_is_406_naming_what_is_available(services: Services) -> None:
    answer = httpx.get(
        services.sparql, params={"query": FILES_QUERY}, headers={"Accept": "image/png"}
    )
    details = error(answer, 406, "not_acceptable")
    assert details["accept"] == "image/png"
    assert "text/csv" in details["available"]
    ask = httpx.get(
        services.sparql,
        params={"query": PREFIX + "ASK { ?s a rc:File }"},
        headers={"Accept": "text/csv"},
    )
    assert "text/csv" not in error(ask, 406, "not_acceptable")["available"]


UPDATE = PREFIX + f"INSERT DATA {{ <{JPEG_FILE}> rc:width 1 }}"


def test_sparql_updates_are_rejected_however_they_are_sent(services: Services) -> None:
    before = services.stored()
    for response in (
        httpx.get(services.sparql, params={"query": UPDATE}),
        httpx.post(services.sparql, data={"update": UPDATE}),
        httpx.post(services.sparql, data={"query": UPDATE}),
        httpx.post(
            services.sparql, content=UPDATE, headers={"Content-Type": "application/sparql-update"}
        ),
    ):
        error(response, 400, "sparql_update_rejected")
    rows = httpx.get(services.sparql, params={"query": FILES_QUERY}).json()["results"]["bindings"]
    assert [row["width"]["value"] for row in rows] == ["640"]
    unchanged(services, before)


def test_a_result_over_the_limit_is_refused_and_no_worker_is_replaced(
    services: Services,
) -> None:
    """Each such query made the service replace the worker that answered it: a reload of the
    whole graph, during which its queries were ``knowledge_loading``."""
    crossed = "SELECT * WHERE { ?s ?p ?o . ?a ?b ?c } LIMIT 2000"
    workers = services.state()["workers"]
    for _ in range(3):
        response = httpx.get(services.sparql, params={"query": crossed})
        assert error(response, 400, "result_too_large") == {"limit": MAX_RESULT_BYTES}
        assert response.json()["error"]["message"] == (
            f"the result is larger than {MAX_RESULT_BYTES} bytes: add a LIMIT"
        )
    assert services.state()["workers"] == workers
    rows = httpx.get(services.sparql, params={"query": crossed.replace("2000", "20")}).json()
    assert len(rows["results"]["bindings"]) == 20


@pytest.mark.parametrize(
    ("params", "status", "code", "details"),
    [
        ({"query": "SELEKT * WHERE { ?s ?p ?o }"}, 400, "sparql_syntax", {}),
        ({"query": ""}, 400, "sparql_syntax", {}),
        ({}, 400, "missing_parameter", {"field": "query"}),
        (
            {"query": "SELECT * { ?s ?p ?o } #" + "x" * 5000},
            413,
            "query_too_large",
            {"size": 5023, "limit": 4096},
        ),
        (
            {"query": "SELECT * WHERE { ?s ?p ?o }", "default-graph-uri": "http://x"},
            400,
            "unsupported_parameter",
            {"field": "default-graph-uri"},
        ),
    ],
)
def test_bad_queries_are_named(
    services: Services, params: dict[str, str], status: int, code: str, details: dict[str, Any]
) -> None:
    assert error(httpx.get(services.sparql, params=params), status, code) == details


def test_a_deeply_nested_query_is_a_syntax_error_and_the_workers_survive(
    services: Services,
) -> None:
    deep = "SELECT * WHERE " + "{" * 2000 + "}" * 2000
    answer = httpx.post(
        services.sparql, content=deep, headers={"Content-Type": "application/sparql-query"}
    )
    error(answer, 400, "sparql_syntax")
    rows = httpx.get(services.sparql, params={"query": FILES_QUERY}).json()["results"]["bindings"]
    assert [row["file"]["value"] for row in rows] == [JPEG_FILE]


class Listener:
    """An HTTP server on a free loopback port that notes each request it is sent: an
    internal service a federated query must never reach."""

    def __init__(self) -> None:
        seen: list[str] = []
        self.requests = seen

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.note()

            def do_POST(self) -> None:
                self.note()

            def note(self) -> None:
                seen.append(f"{self.command} {self.path}")
                self.send_response(500)
                self.end_headers()

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]

    def __enter__(self) -> Listener:
        threading.Thread(target=self.server.serve_forever, daemon=True).start()
        return self

    def __exit__(self, *_: object) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.mark.parametrize(
    ("template", "reason"),
    [
        (
            "SELECT * WHERE { # \r SERVICE <http://127.0.0.1:{port}/internal> { ?a ?b ?c } \n}",
            "a carriage return not followed by a line feed (at character 19) is refused",
        ),
        (
            'SELECT * WHERE { BIND("a\\u005C" AS ?x) '
            "SERVICE <http://127.0.0.1:{port}/internal> { ?a ?b ?c } BIND('\" AS ?v) #' AS ?w) \n}",
            "a \\u escape (at character 24) is refused",
        ),
    ],
)
def test_a_service_call_hidden_from_the_check_reaches_nothing(
    services: Services, template: str, reason: str
) -> None:
    """rdflib's parse, which the check reads, saw a comment or one long string where
    Oxigraph, which runs the text, saw SERVICE: the storage service POSTed to the address the
    query named and answered with what it got there. Sent unsigned, as anyone can."""
    before = services.stored()
    with Listener() as listener:
        query = template.replace("{port}", str(listener.port))
        answer = httpx.get(services.sparql, params={"query": query})
        error(answer, 400, "sparql_query_refused")
        message = answer.json()["error"]["message"]
        assert message.startswith(reason), message
        assert "SERVICE" in message
        assert listener.requests == []
    unchanged(services, before)


def test_a_form_of_too_many_fields_is_named_not_a_500(services: Services) -> None:
    """parse_qsl raised ValueError past 32 fields, answered 500 internal_error."""
    before = services.stored()
    form = "&".join(["query=" + UPDATE.replace(" ", "+")] + [f"f{i}=x" for i in range(40)])
    answer = httpx.post(
        services.sparql,
        content=form,
        headers={"Content-Type": "application/x-www-form-urlencoded"},
    )
    assert error(answer, 400, "invalid_parameter") == {"field": "body", "fields": 41, "limit": 32}
    assert "41 fields" in answer.json()["error"]["message"]
    unchanged(services, before)


SPARQL_BODY_LIMIT = 3 * 4096 + 4096
"""A query of the 4,096 bytes these services allow, percent-encoded, and the form's other
fields."""


def test_a_form_as_large_as_its_query_may_be_percent_encoded_is_answered(
    services: Services,
) -> None:
    query = FILES_QUERY + " #" + "é" * ((4096 - len(FILES_QUERY) - 2) // 2)
    encoded = "".join(f"%{byte:02X}" for byte in query.encode())
    form = f"query={encoded}&format=json"
    assert len(query.encode()) == 4096
    assert len(form) <= SPARQL_BODY_LIMIT
    answer = httpx.post(
        services.sparql,
        content=form,
        headers={"Content-Type": "application/x-www-form-urlencoded"},
    )
    assert answer.status_code == 200, answer.text
    rows = answer.json()["results"]["bindings"]
    assert [row["file"]["value"] for row in rows] == [JPEG_FILE]


@pytest.mark.parametrize("chunked", [False, True])
def test_a_sparql_body_past_what_a_query_may_be_is_refused_before_it_is_parsed(
    services: Services, chunked: bool
) -> None:
    """The unsigned SPARQL route took the service's 16 MiB body: a form of escapes was
    parsed on the event loop (0.8 s each 4 MiB, every route of the service waiting) before
    its query was found too large. Refused by Content-Length, or once past the bound."""
    form = b"query=" + b"%41" * (1 << 20)
    content: bytes | Iterator[bytes] = (
        iter([form[i : i + 65536] for i in range(0, len(form), 65536)]) if chunked else form
    )
    answer = httpx.post(
        services.sparql,
        content=content,
        headers={"Content-Type": "application/x-www-form-urlencoded"},
    )
    details = error(answer, 413, "payload_too_large")
    assert details["limit"] == SPARQL_BODY_LIMIT
    assert ("header" in details) is not chunked
    rows = httpx.get(services.sparql, params={"query": FILES_QUERY}).json()["results"]["bindings"]
    assert [row["file"]["value"] for row in rows] == [JPEG_FILE]


def test_a_post_that_is_neither_a_form_nor_a_query_is_415(services: Services) -> None:
    answer = httpx.post(
        services.sparql, content=b"{}", headers={"Content-Type": "application/json"}
    )
    assert error(answer, 415, "unsupported_media_type")["received"] == "application/json"


SLOW = "SELECT (COUNT(*) AS ?n) WHERE { ?a ?b ?c . ?d ?e ?f . ?g ?h ?i . ?j ?k ?l . ?m ?n2 ?o }"


def test_a_query_past_its_time_is_stopped_while_other_queries_are_answered(
    services: Services,
) -> None:
    outcome: dict[str, httpx.Response] = {}
    slow = threading.Thread(
        target=lambda: outcome.setdefault(
            "slow", httpx.get(services.sparql, params={"query": SLOW}, timeout=60)
        )
    )
    before = services.state()["workers"]
    slow.start()
    wait_for(lambda: services.state()["workers"]["busy"] == 1, "the slow query to start")
    quick = httpx.get(services.sparql, params={"query": FILES_QUERY}, timeout=60)
    assert quick.json()["results"]["bindings"][0]["file"]["value"] == JPEG_FILE
    slow.join()
    details = error(outcome["slow"], 503, "query_timeout")
    assert details == {"timeout_s": TIMEOUT_S}
    assert outcome["slow"].headers["retry-after"] == "1"
    # Only the query's own process was killed: the worker is idle at once, nothing reloads.
    after = services.state()["workers"]
    assert (after["ready"], after["busy"]) == (2, 0)
    assert (after["stopped"], after["replaced"]) == (before["stopped"] + 1, before["replaced"])
    again = httpx.get(services.sparql, params={"query": FILES_QUERY}, timeout=60)
    assert again.json()["results"]["bindings"][0]["width"]["value"] == "640"


def test_a_flood_of_slow_queries_keeps_the_service_ready(services: Services) -> None:
    """Each slow query's worker used to be killed at the timeout and reload the graph.
    Readiness followed the workers, so a flood of slow queries flapped the whole service (its
    records, ingest and proofs included) to 503 with every replacement; each query waiting
    for a free worker held one of the threads every other route needs; and while the
    workers reloaded, everyone's queries were 503 ``knowledge_loading``. Now only each
    query's own process is killed, and the flood's address has one of the two workers: another
    client's queries are answered while it goes on."""
    before = services.state()["workers"]

    def slow_query(client: httpx.Client) -> httpx.Response:
        return client.get(services.sparql, params={"query": SLOW})

    readiness: list[int] = []
    answered: list[float] = []
    with flooding(slow_query, 12) as flood, httpx.Client(timeout=10) as probe:
        deadline = time.monotonic() + 3 * TIMEOUT_S
        while time.monotonic() < deadline:
            readiness.append(probe.get(f"{services.storage.url}/readyz").status_code)
            asked = time.monotonic()
            quick = probe.get(services.sparql, params={"query": FILES_QUERY})
            assert quick.json()["results"]["bindings"][0]["file"]["value"] == JPEG_FILE
            answered.append(time.monotonic() - asked)
            time.sleep(0.05)
        node = probe.get(f"{services.storage.url}/v1/node")
    assert set(readiness) == {200}
    assert node.status_code == 200
    assert max(answered) < TIMEOUT_S
    codes = {(answer.status_code, answer.json()["error"]["code"]) for answer in flood.answers}
    assert (503, "query_timeout") in codes
    assert (429, "rate_limited") in codes
    assert codes <= {(503, "query_timeout"), (429, "rate_limited"), (503, "busy")}
    for answer in flood.answers:
        assert answer.headers["retry-after"] == "1"
    after = services.state()["workers"]
    assert after["replaced"] == before["replaced"]
    assert after["stopped"] > before["stopped"]
    quick = httpx.get(services.sparql, params={"query": FILES_QUERY}, timeout=60)
    assert quick.json()["results"]["bindings"][0]["file"]["value"] == JPEG_FILE


# ----- application discovery -----


def test_applications_consuming_jpeg_are_found_with_their_ports(services: Services) -> None:
    with services.knowledge() as knowledge:
        found = knowledge.applications("image/jpeg")
        assert found == [
            {
                "iri": APP,
                "cid": APP.removeprefix("ipfs://"),
                "name": "blur_faces",
                "version": "1.2.0",
                "inputs": [
                    {
                        "name": "image",
                        "iri": f"{APP}#input-image",
                        "media_type": "image/jpeg",
                        "template": None,
                        "attributes": ["height", "width"],
                    }
                ],
                "outputs": [
                    {
                        "name": "image",
                        "iri": f"{APP}#output-image",
                        "media_type": "image/jpeg",
                        "template": None,
                        "attributes": ["height", "width"],
                    }
                ],
            }
        ]
        iri = "https://www.iana.org/assignments/media-types/image/jpeg"
        assert knowledge.applications(iri) == found
        assert knowledge.applications("image/jpeg", produces="image/jpeg") == found
        assert knowledge.applications("image/jpeg", produces="text/plain") == []
        assert knowledge.applications("image/png") == []


@pytest.mark.parametrize(
    ("query", "field"),
    [
        ("consumes=jpeg", "consumes"),
        ("consumes=image/jpeg&produces=ipfs://nope", "produces"),
        ("consumes=%3E%20.%20%7D", "consumes"),
        ("consumes=image/a%5Eb", "consumes"),  # RFC 6838 allows ^, an IRI does not
        ("consumes=image/jpeg&produces=text/a%5Eb", "produces"),
    ],
)
def test_a_bad_type_is_named(services: Services, query: str, field: str) -> None:
    answer = httpx.get(f"{services.storage.url}/v1/knowledge/applications?{query}")
    assert error(answer, 400, "invalid_parameter")["field"] == field


def test_a_limit_out_of_range_or_no_type_is_refused(services: Services) -> None:
    url = f"{services.storage.url}/v1/knowledge/applications"
    for query in ("consumes=image/jpeg&limit=0", "consumes=image/jpeg&limit=1001", ""):
        answer = httpx.get(f"{url}?{query}")
        assert answer.status_code in (400, 422), answer.text
        assert answer.json()["error"]["details"]


def test_the_sdk_refuses_an_invalid_description_before_sending_anything(
    services: Services,
) -> None:
    before = services.stored()
    broken = semantic.parse_canonical(example("task").canonical().replace(b'"3"^^', b'"0"^^'))
    with services.cas() as cas, services.knowledge() as knowledge:
        with pytest.raises(semantic.DescriptionInvalidError, match="rc:replication"):
            knowledge.store(broken, cas)
        with pytest.raises(ApiError) as caught:
            knowledge.add(str(broken.cid()))
    assert caught.value.code == "description_not_found"
    unchanged(services, before)
