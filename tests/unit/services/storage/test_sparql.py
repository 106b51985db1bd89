"""SPARQL workers: content negotiation, and the pool of real worker processes over description
files (additions seen by the next query, a query past its deadline killed and replaced)."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from robocloud import semantic
from robocloud.cid import CID
from robocloud.unixfs import import_bytes
from services.common.durable import atomic_write
from services.storage.sparql import (
    NotAcceptableError,
    QueryRefusedError,
    QuerySyntaxError,
    QueryTimeoutError,
    ResultTooLargeError,
    SparqlWorkers,
    UpdateRejectedError,
    WorkerFailedError,
    WorkersUnavailableError,
    choose_format,
    negotiate,
)
from tests.procs import REPO
from tests.waiting import wait_for

EXAMPLES = REPO / "ontology" / "examples"
FILE = "ipfs://bafkreifhyd2reqnaxb6vmuv3gwnyum4osowzkclmxa2qdsj3fhkderxyem"
PREFIX = "PREFIX rc: <https://w3id.org/robocloud#>\n"


@pytest.mark.parametrize(
    ("accept", "expected"),
    [
        (None, "application/sparql-results+json"),
        ("", "application/sparql-results+json"),
        ("*/*", "application/sparql-results+json"),
        ("text/csv", "text/csv"),
        ("TEXT/CSV", "text/csv"),
        ("text/csv;q=0.2, application/sparql-results+xml;q=0.8", "application/sparql-results+xml"),
        ("text/csv;q=0, */*;q=0.1", "application/sparql-results+json"),
        ("image/png, text/*;q=0.5", "text/csv"),
        ("application/*", "application/sparql-results+json"),
        ("text/csv;q=abc, application/json", "application/json"),
    ],
)
def test_select_formats_follow_the_accept_header(accept: str | None, expected: str) -> None:
    assert choose_format("SELECT", accept, None) == expected


def test_a_refused_or_unknown_type_is_not_acceptable() -> None:
    with pytest.raises(NotAcceptableError) as caught:
        negotiate("image/png, text/csv;q=0", ["text/csv"], "text/csv")
    assert caught.value.available == ["text/csv"]
    with pytest.raises(NotAcceptableError):
        choose_format("ASK", "text/csv", None)
    with pytest.raises(NotAcceptableError):
        choose_format("CONSTRUCT", "application/sparql-results+json", None)


def test_graphs_default_to_turtle_and_format_parameters_win() -> None:
    assert choose_format("CONSTRUCT", None, None) == "text/turtle"
    assert choose_format("DESCRIBE", "application/rdf+xml", None) == "application/rdf+xml"
    assert choose_format("SELECT", "text/csv", "json") == "application/sparql-results+json"
    assert choose_format("CONSTRUCT", None, "xml") == "application/rdf+xml"
    assert choose_format("SELECT", None, "text/csv") == "text/csv"


def write(directory: Path, description: semantic.Description) -> str:
    cid = str(description.cid())
    atomic_write(directory / f"{cid}.nt", description.canonical())
    return cid


def example(kind: str) -> semantic.Description:
    return semantic.parse_description((EXAMPLES / f"{kind}.ttl").read_bytes())


@pytest.fixture(params=["memory", "oxigraph"])
def pool(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[SparqlWorkers]:
    write(tmp_path, example("file"))
    (tmp_path / "bafkreigarbage.nt").write_bytes(b"not a description\n")  # not its CID
    garbage = b'<https://a.example/s> <https://a.example/p> "unterminated .\n'
    (tmp_path / f"{import_bytes(garbage)[1]}.nt").write_bytes(garbage)  # its CID, not RDF
    workers = SparqlWorkers(
        tmp_path,
        workers=2,
        timeout_s=3,
        max_result_bytes=1 << 20,
        memory_bytes=1 << 31,
        store=request.param,
    )
    workers.start()
    wait_for(lambda: workers.describe()["ready"] == 2, "both workers")
    yield workers
    workers.close()


def select(pool: SparqlWorkers, query: str) -> list[dict[str, str]]:
    media, body = pool.query(PREFIX + query, None)
    assert media == "application/sparql-results+json"
    rows = json.loads(body)["results"]["bindings"]
    return [{name: value["value"] for name, value in row.items()} for row in rows]


def test_workers_load_the_files_skip_what_is_not_a_description_and_see_additions(
    pool: SparqlWorkers,
) -> None:
    kinds = "SELECT ?s WHERE { ?s a ?kind } ORDER BY ?s"
    assert select(pool, kinds) == [{"s": FILE}]
    cid = write(pool.directory, example("application"))
    pool.add([cid])
    for _ in range(4):  # every worker sees it, whichever answers
        assert len(select(pool, "SELECT ?a WHERE { ?a a rc:Application }")) == 1


def test_applications_are_found_by_media_type_or_by_record_template(pool: SparqlWorkers) -> None:
    template = "bafkreigyfykq6j7zji5odgbwfjasn6pbbpx5a4irvf74j62376sqyl3kbm"
    records = semantic.application_description(
        "bafkreicyps4ybl3w7xd6ki3j7ufz3etn74tgs5vw7cwgghrvr7wmjh7yz4",
        "imu_filter",
        "2",
        inputs=[semantic.Port("imu", template=template)],
        outputs=[semantic.Port("report", media_type="application/json")],
    )
    pool.add([write(pool.directory, records), write(pool.directory, example("application"))])
    rows = pool.application_rows(f"ipfs://{template}")
    assert sorted({(row[1], row[3], row[5], row[6], row[7]) for row in rows}) == [
        ("imu_filter", "input", "imu", None, f"ipfs://{template}"),
        (
            "imu_filter",
            "output",
            "report",
            "https://www.iana.org/assignments/media-types/application/json",
            None,
        ),
    ]
    jpeg = pool.application_rows("https://www.iana.org/assignments/media-types/image/jpeg")
    assert {row[1] for row in jpeg} == {"blur_faces"}
    assert pool.application_rows("https://www.iana.org/assignments/media-types/image/gif") == []


def test_syntax_errors_and_updates_are_told_apart(pool: SparqlWorkers) -> None:
    with pytest.raises(QuerySyntaxError, match=r"not a SPARQL 1\.1 query"):
        pool.query("SELECT WHERE", None)
    with pytest.raises(UpdateRejectedError):
        pool.query(PREFIX + "DELETE WHERE { ?s ?p ?o }", None)
    # Nothing but whitespace, comments or prefixes parses as an empty update: no query.
    for empty in ("", "  \n", "# nothing", PREFIX):
        with pytest.raises(QuerySyntaxError, match="it holds no query"):
            pool.query(empty, None)
    assert pool.describe()["replaced"] == 0


@pytest.mark.parametrize(
    ("query", "message"),
    [
        ("SELECT * WHERE { SERVICE <http://127.0.0.1:1/> { ?s ?p ?o } }", "SERVICE is refused"),
        (
            "SELECT * WHERE { ?s ?p ?o OPTIONAL { { SERVICE SILENT <http://x/> { ?s ?p ?o } } } }",
            "SERVICE is refused",
        ),
        ("SELECT * FROM <http://127.0.0.1:1/g> WHERE { ?s ?p ?o }", "FROM and FROM NAMED"),
        ("ASK FROM NAMED <file:///etc/passwd> { ?s ?p ?o }", "FROM and FROM NAMED"),
    ],
)
def test_a_query_that_would_fetch_from_elsewhere_is_refused(
    pool: SparqlWorkers, query: str, message: str
) -> None:
    with pytest.raises(QueryRefusedError, match=message):
        pool.query(query, None)


CR_COMMENT = "SELECT * WHERE { # \r SERVICE <http://127.0.0.1:1/> { ?a ?b ?c } \n}"
ESCAPED_QUOTE = (
    'SELECT * WHERE { BIND("a\\u005C" AS ?x) SERVICE <http://127.0.0.1:1/> { ?a ?b ?c } '
    "BIND('\" AS ?v) #' AS ?w) \n}"
)


@pytest.mark.parametrize(
    ("query", "message"),
    [
        (CR_COMMENT, r"a carriage return not followed by a line feed \(at character 19\)"),
        (ESCAPED_QUOTE, r"a \\u escape \(at character 24\)"),
        ('ASK { ?s ?p "\\U0001F600" }', r"a \\u escape"),
    ],
)
def test_text_rdflib_and_oxigraph_would_read_apart_is_refused(
    pool: SparqlWorkers, query: str, message: str
) -> None:
    """Each of the first two hid a SERVICE from the check on rdflib's parse, and Oxigraph,
    parsing the text again, ran it: a comment that rdflib ends at a line feed only, and an
    escape rdflib expands before parsing (to a backslash that swallows a quote)."""
    with pytest.raises(QueryRefusedError, match=message):
        pool.query(query, None)


def test_a_comment_ended_by_crlf_is_read_alike_and_taken(pool: SparqlWorkers) -> None:
    _, body = pool.query(PREFIX + "ASK { # a comment\r\n ?s a rc:File }", None)
    assert json.loads(body)["boolean"] is True


def test_a_worker_cannot_open_an_ip_socket() -> None:
    """The net behind the text checks: whatever a parser lets through, no query can make a
    worker (or an executor it forks) send a request. Unix sockets stay open to it."""
    probe = (
        "import socket\n"
        "from services.storage.sparql import _forbid_network\n"
        "assert _forbid_network()\n"
        "socket.socket(socket.AF_UNIX).close()\n"
        "for family in (socket.AF_INET, socket.AF_INET6):\n"
        "    try:\n"
        "        socket.socket(family)\n"
        "    except PermissionError:\n"
        "        continue\n"
        "    raise SystemExit(f'{family!r} opened')\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr


def test_a_query_past_its_deadline_is_killed_and_its_worker_free_at_once(
    pool: SparqlWorkers,
) -> None:
    """The query runs in a process forked from its worker: killing that process stops it,
    and the worker, which keeps its graph, takes the next query without reloading."""
    patterns = " . ".join(f"?s{i} ?p{i} ?o{i}" for i in range(10))
    slow = f"SELECT (COUNT(*) AS ?n) WHERE {{ {patterns} }}"
    failures: list[Exception] = []

    def run() -> None:
        try:
            pool.query(slow, None)
        except QueryTimeoutError as exc:
            failures.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    wait_for(lambda: pool.describe()["busy"] == 1, "the slow query to start")
    _, body = pool.query(PREFIX + "ASK { ?s a rc:File }", None)
    assert json.loads(body)["boolean"] is True
    thread.join()
    assert [str(exc) for exc in failures] == ["the query did not finish within 3 s; it was stopped"]
    assert pool.describe() == {
        "ready": 2,
        "busy": 0,
        "replaced": 0,
        "stopped": 1,
        "refreshed": 0,
        "start_failures": 0,
    }
    for _ in range(2):  # both workers, the one that ran the slow query included
        _, body = pool.query(PREFIX + "ASK { ?s a rc:File }", None)
        assert json.loads(body)["boolean"] is True


def test_a_result_over_the_limit_is_refused_by_the_worker_which_is_kept(
    tmp_path: Path,
) -> None:
    """The worker sent the whole answer and the service, reading no more than the limit,
    replaced it: a reload of every description (seconds of a core, 10.7 s at 10,000 files)
    for a query anyone can write, while its queries got ``knowledge_loading``."""
    write(tmp_path, example("file"))
    workers = SparqlWorkers(
        tmp_path, workers=1, timeout_s=10, max_result_bytes=10_000, memory_bytes=1 << 31
    )
    workers.start()
    try:
        wait_for(lambda: workers.describe()["ready"] == 1, "the worker")
        everything_twice = "SELECT * WHERE { ?s1 ?p1 ?o1 . ?s2 ?p2 ?o2 }"
        for _ in range(3):
            with pytest.raises(ResultTooLargeError) as refused:
                workers.query(everything_twice, None)
            assert str(refused.value) == "the result is larger than 10000 bytes: add a LIMIT"
            assert workers.describe()["ready"] == 1
        assert workers.describe()["replaced"] == 0
        _, body = workers.query(everything_twice + " LIMIT 2", None)
        assert len(json.loads(body)["results"]["bindings"]) == 2
    finally:
        workers.close()


def test_an_idle_worker_forks_a_fresh_executor_that_shares_its_pages_again(
    tmp_path: Path,
) -> None:
    """A query copies the pages it writes out of what the executor shares with its worker;
    while the executor lives, both keep their copies. After ``idle_refresh_s`` with no query
    the worker forks a new executor, and the pair shares those pages again."""
    for index in range(300):
        cid = CID.from_block(f"file-{index}".encode())
        write(tmp_path, semantic.file_description(cid, "image/png", 1000 + index))
    workers = SparqlWorkers(
        tmp_path,
        workers=1,
        timeout_s=10,
        max_result_bytes=16 << 20,
        memory_bytes=1 << 31,
        store="memory",
        idle_refresh_s=1.0,
    )
    workers.start()
    try:
        wait_for(lambda: workers.describe()["ready"] == 1, "the worker")
        worker = workers._children[0].process.pid
        first = executor_of(worker)
        assert select(workers, "SELECT (COUNT(*) AS ?n) WHERE { ?f a rc:File }") == [{"n": "300"}]
        workers.query(PREFIX + "CONSTRUCT { ?s ?p ?o } WHERE { ?s ?p ?o }", None)
        copied = private_mib(first)
        wait_for(lambda: workers.describe()["refreshed"] == 1, "the executor to be refreshed")
        fresh = executor_of(worker)
        assert fresh != first
        assert private_mib(fresh) < copied
        assert select(workers, "SELECT (COUNT(*) AS ?n) WHERE { ?f a rc:File }") == [{"n": "300"}]
        # Refreshed once per idle spell: an executor that answered nothing is left alone.
        wait_for(lambda: workers.describe()["refreshed"] == 2, "the second refresh")
        third = executor_of(worker)
        time.sleep(2.5)
        assert executor_of(worker) == third
        assert workers.describe()["refreshed"] == 2
    finally:
        workers.close()


def executor_of(worker: int) -> int:
    """The pid of the worker's one child, its executor, once there is one: the worker says it
    may say it is ready before its executor shows in /proc (a CI run found none there)."""

    def children() -> list[str] | None:
        found = Path(f"/proc/{worker}/task/{worker}/children").read_text().split()
        return found if len(found) == 1 else None

    (child,) = wait_for(children, "the worker's executor")
    return int(child)


def private_mib(pid: int) -> float:
    """What of the process's memory no other process shares."""
    lines = Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:]
    fields = dict(line.split(":", 1) for line in lines)
    return sum(int(fields[name].split()[0]) for name in ("Private_Clean", "Private_Dirty")) / 1024


def one_worker(directory: Path, timeout_s: float) -> SparqlWorkers:
    write(directory, example("file"))
    workers = SparqlWorkers(
        directory,
        workers=1,
        timeout_s=timeout_s,
        max_result_bytes=1 << 20,
        memory_bytes=1 << 31,
        store="memory",
    )
    workers.start()
    return workers


def asks_a_file(workers: SparqlWorkers) -> bool:
    _, body = workers.query(PREFIX + "ASK { ?s a rc:File }", None)
    answer: bool = json.loads(body)["boolean"]
    return answer


@contextlib.contextmanager
def one_hung_worker(directory: Path) -> Iterator[tuple[SparqlWorkers, subprocess.Popen[bytes]]]:
    """A pool of one worker with a 2 s deadline, its worker stopped (SIGSTOP) once ready; the
    stopped process is killed and the pool closed afterwards."""
    workers = one_worker(directory, timeout_s=2)
    hung: subprocess.Popen[bytes] | None = None
    try:
        wait_for(lambda: workers.describe()["ready"] == 1, "the worker")
        hung = workers._children[0].process
        hung.send_signal(signal.SIGSTOP)
        yield workers, hung
    finally:
        if hung is not None and hung.poll() is None:
            hung.send_signal(signal.SIGCONT)
            hung.kill()
        workers.close()


def test_a_query_that_fills_the_pipe_of_a_hung_worker_times_out_and_the_worker_is_replaced(
    tmp_path: Path,
) -> None:
    """A stopped worker takes nothing off its pipe, which holds 64 KiB: the write of a query of
    the accepted maximum size has the query's deadline too (it blocked for good)."""
    with one_hung_worker(tmp_path) as (workers, hung):
        head = PREFIX + "ASK { ?s a rc:File }\n#"
        big = head + "x" * (64 * 1024 - len(head))
        failures: list[Exception] = []

        def run() -> None:
            try:
                workers.query(big, None)
            except QueryTimeoutError as exc:
                failures.append(exc)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        thread.join(60)
        assert not thread.is_alive(), "the query to the hung worker never returned"
        assert [str(exc) for exc in failures] == [
            "the query did not finish within 2 s; it was stopped"
        ]
        wait_for(lambda: workers.describe()["ready"] == 1, "the replacement worker")
        assert workers.describe()["replaced"] == 1
        assert workers._children[0].process is not hung
        assert asks_a_file(workers)


def test_a_replacement_lives_on_when_the_thread_whose_query_replaced_it_ends(
    tmp_path: Path,
) -> None:
    """Linux's parent-death signal follows the thread that forked a worker: a replacement was
    forked on the thread of the query that timed out, and killed when that thread ended (anyio
    ends an idle one after 10 s), so the next query failed and reloaded every description."""
    with one_hung_worker(tmp_path) as (workers, hung):

        def query_then_wait_for_the_replacement() -> None:
            with contextlib.suppress(QueryTimeoutError):
                workers.query(PREFIX + "ASK { ?s a rc:File }", None)
            wait_for(lambda: workers.describe()["ready"] == 1, "the replacement worker")

        thread = threading.Thread(target=query_then_wait_for_the_replacement, daemon=True)
        thread.start()
        thread.join(60)
        assert not thread.is_alive()
        replacement = workers._children[0].process
        assert replacement is not hung
        time.sleep(1.0)
        assert replacement.poll() is None, "the replacement died with the thread"
        assert asks_a_file(workers)
        assert workers.describe()["replaced"] == 1


def test_a_worker_whose_replacement_could_not_be_forked_is_started_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fork refused (EAGAIN) while replacing a dead worker left the pool a worker short for
    good, and ready while every query failed; it is tried again until it starts."""
    workers = one_worker(tmp_path, timeout_s=5)
    try:
        wait_for(lambda: workers.describe()["ready"] == 1, "the worker")
        real = subprocess.Popen
        refused: list[int] = []
        refusing = threading.Event()
        refusing.set()

        def flaky(*args: object, **kwargs: object) -> subprocess.Popen[bytes]:
            if refusing.is_set():
                refused.append(1)
                raise BlockingIOError(errno.EAGAIN, os.strerror(errno.EAGAIN))
            return real(*args, **kwargs)  # type: ignore[call-overload, no-any-return]

        monkeypatch.setattr("services.storage.sparql.subprocess.Popen", flaky)
        dead = workers._children[0].process
        dead.kill()
        dead.wait()
        with pytest.raises(WorkerFailedError):
            asks_a_file(workers)
        assert not workers.loaded()  # no worker lives: not ready
        wait_for(lambda: len(refused) >= 2, "the start to be tried again")
        refusing.clear()
        wait_for(lambda: workers.describe()["ready"] == 1, "the worker started again")
        assert len(workers._children) == 1
        assert workers.loaded()
        assert asks_a_file(workers)
    finally:
        workers.close()


def test_workers_that_die_while_loading_are_replaced_ever_more_slowly(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A graph larger than the workers' memory ends each worker while it loads; replaced a
    second later every time, two of them loading in turn held both cores for good. Here 16 MiB
    ends a worker before it has imported rdflib."""
    write(tmp_path, example("file"))
    workers = SparqlWorkers(
        tmp_path, workers=1, timeout_s=5, max_result_bytes=1 << 20, memory_bytes=16 << 20
    )
    caplog.set_level("ERROR", logger="robocloud.storage.sparql")
    workers.start()
    try:
        wait_for(lambda: workers.describe()["start_failures"] >= 3, "three failed starts", 30)
        delays = [
            record.args[1]
            for record in caplog.records
            if record.getMessage().startswith("a SPARQL worker did not start")
        ]
        assert delays[:3] == [1.0, 2.0, 4.0]
        assert "ROBOCLOUD_KNOWLEDGE_WORKER_MEMORY_BYTES" in caplog.records[0].getMessage()
        assert not workers.loaded()
        with pytest.raises(WorkersUnavailableError):
            asks_a_file(workers)
    finally:
        workers.close()
