"""SPARQL over the knowledge base, in worker processes that can be stopped.

rdflib evaluates a query in Python, and nothing inside it checks a clock: a cross product of
every file with every file, or a regular expression that backtracks for ever, holds its thread
until it is done. So queries never run in the service's process. Each worker is a child
process (``python -m services.storage.sparql``) holding its own copy of the graph, read from
the description files; a query goes to an idle worker with a deadline. The worker does not
evaluate queries itself: its executor does, a process forked from it that shares its graph.
A query that misses its deadline is stopped by killing the executor; the worker forks a new
one (10 ms for a 180 MiB worker) and is free again at once. Before, the worker itself was
killed and replaced, and reloading the graph took seconds of CPU: anyone sending slow queries
kept every worker reloading, and the knowledge base answered ``knowledge_loading`` to
everyone. (A fork per query instead cost 10-35 ms a query; the worker is single-threaded, so
forking it is safe.) Memory is bounded too (``RLIMIT_AS``, per process), and each process
dies with its parent (``PR_SET_PDEATHSIG``).

An executor shares its pages with its worker only until it writes to them, and a query writes
all over the heap: one count over 10,000 files left 33 MiB private to each of the two
processes, a large SELECT 105 MiB, and the pair then held twice the worker's memory for as
long as the executor lived. So a worker idle for ``idle_refresh_s`` after a query is asked to
fork a fresh executor (``refresh``), sharing every page again; a busy one keeps its executor,
whose copied pages the next query would only copy again.

Parent and worker speak pickled messages framed by a 4-byte length over the worker's stdin and
stdout; the worker is our own code, started by us, so pickle is safe here. Descriptions added
after a worker started reach it as ``load`` messages sent before its next query, so a query
always sees every description acknowledged before it was sent.

Result formats follow the SPARQL 1.1 Protocol: result sets as SPARQL JSON, XML or CSV,
graphs (CONSTRUCT, DESCRIBE) as Turtle, N-Triples or RDF/XML, chosen from the Accept header.
"""

from __future__ import annotations

import contextlib
import ctypes
import enum
import errno
import logging
import os
import pickle
import platform
import queue
import re
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from services.common.lifetime import die_with_parent, limit_memory

log = logging.getLogger("robocloud.storage.sparql")

RESULT_SET_TYPES = {
    "application/sparql-results+json": "json",
    "application/json": "json",
    "application/sparql-results+xml": "xml",
    "application/xml": "xml",
    "text/csv": "csv",
    "text/xml": "xml",
}
"""Media types a SELECT or ASK answer can take, with rdflib's result serializer for each."""
GRAPH_TYPES = {
    "text/turtle": "turtle",
    "application/x-turtle": "turtle",
    "application/n-triples": "nt",
    "text/plain": "nt",
    "application/rdf+xml": "xml",
    "application/xml": "xml",
    "text/xml": "xml",
}
"""Media types a CONSTRUCT or DESCRIBE answer can take, with rdflib's graph serializer."""
DEFAULT_RESULT_SET = "application/sparql-results+json"
DEFAULT_GRAPH = "text/turtle"
FORMAT_PARAMETER = {
    "json": ("application/sparql-results+json", "text/turtle"),
    "xml": ("application/sparql-results+xml", "application/rdf+xml"),
    "csv": ("text/csv", "text/turtle"),
    "turtle": ("application/sparql-results+json", "text/turtle"),
    "n3": ("application/sparql-results+json", "text/turtle"),
    "rdf+xml": ("application/sparql-results+xml", "application/rdf+xml"),
}
"""``format``/``output`` parameters some clients (SPARQLWrapper) send beside Accept."""

PREFIXES = """PREFIX rc: <https://w3id.org/robocloud#>
PREFIX rdf: <http://www.w3.org/1999/02/22-rdf-syntax-ns#>
"""
APPLICATIONS_QUERY = (
    PREFIXES
    + """SELECT ?app ?name ?version ?direction ?port ?portName ?mediaType ?template ?attribute
WHERE {
    ?app rc:input ?wanted .
    ?wanted rc:mediaType|rc:portTemplate ?consumes .
    ?app rc:name ?name ; rc:version ?version .
    { ?app rc:input ?port . BIND ("input" AS ?direction) }
    UNION
    { ?app rc:output ?port . BIND ("output" AS ?direction) }
    ?port rc:name ?portName .
    OPTIONAL { ?port rc:mediaType ?mediaType }
    OPTIONAL { ?port rc:portTemplate ?template }
    OPTIONAL { ?port rc:requiresAttribute ?attribute }
}"""
)
"""Applications with an input of type ``?consumes``, one row per port and attribute."""
WARM_QUERIES = (
    APPLICATIONS_QUERY,
    PREFIXES + "SELECT ?s ?p ?o WHERE { ?s ?p ?o . FILTER (isIRI(?s)) } ORDER BY ?s LIMIT 1",
    PREFIXES + "ASK { ?s a rc:File }",
    PREFIXES + "CONSTRUCT { ?s ?p ?o } WHERE { ?s ?p ?o } LIMIT 1",
)
"""Parsed when a worker starts: rdflib's first parse builds its grammar (seconds)."""


class SparqlError(Exception):
    """Base of the knowledge base's query errors."""


class QuerySyntaxError(SparqlError):
    """The query is not SPARQL 1.1."""


class UpdateRejectedError(SparqlError):
    """A SPARQL update sent to the query endpoint, which is read-only."""


class QueryTooLargeError(SparqlError):
    def __init__(self, size: int, limit: int) -> None:
        super().__init__(f"the query has {size} bytes, more than the limit of {limit}")
        self.size = size
        self.limit = limit


class ResultTooLargeError(SparqlError):
    def __init__(self, limit: int) -> None:
        super().__init__(f"the result is larger than {limit} bytes: add a LIMIT")
        self.limit = limit


class QueryTimeoutError(SparqlError):
    """The query did not finish within the budget; its worker was stopped."""

    def __init__(self, timeout_s: float, *, waiting: bool = False) -> None:
        what = "no query worker was free" if waiting else "the query did not finish"
        super().__init__(f"{what} within {timeout_s:g} s; it was stopped")
        self.timeout_s = timeout_s


class QueryRefusedError(SparqlError):
    """A query that would reach outside the knowledge base (SERVICE, FROM)."""


class NotAcceptableError(SparqlError):
    def __init__(self, accept: str, available: Sequence[str]) -> None:
        super().__init__(f"no result format matches Accept: {accept[:200]}")
        self.accept = accept
        self.available = list(available)


class WorkerFailedError(SparqlError):
    """A worker died or answered nonsense (out of memory, a crash); it was replaced."""


class WorkersUnavailableError(SparqlError):
    """No worker has started yet (the service is still loading its descriptions)."""


# ----- content negotiation (pure) -----


def negotiate(accept: str | None, available: Sequence[str], default: str) -> str:
    """The media type in ``available`` the Accept header prefers (RFC 9110 q-values).

    No header, or ``*/*`` alone, gives ``default``; nothing acceptable raises
    ``NotAcceptableError``.
    """
    if not accept or not accept.strip():
        return default
    ranges: list[tuple[float, int, str]] = []
    for position, item in enumerate(accept.split(",")[:64]):
        parts = [part.strip() for part in item.split(";")]
        media = parts[0].lower()
        quality = 1.0
        for parameter in parts[1:]:
            name, _, value = parameter.partition("=")
            if name.strip().lower() == "q":
                try:
                    quality = float(value)
                except ValueError:
                    quality = 0.0
        if media and quality > 0:
            ranges.append((-quality, position, media))
    for _, _, media in sorted(ranges):
        if media == "*/*":
            return default
        if media.endswith("/*"):
            prefix = media[:-1]
            if default.startswith(prefix):
                return default
            for candidate in available:
                if candidate.startswith(prefix):
                    return candidate
        elif media in available:
            return media
    raise NotAcceptableError(accept, available)


def choose_format(query_kind: str, accept: str | None, format_parameter: str | None) -> str:
    """The media type of the answer to a query of ``query_kind`` (SELECT, ASK, CONSTRUCT...)."""
    graph = query_kind in ("CONSTRUCT", "DESCRIBE")
    if format_parameter:
        hinted = FORMAT_PARAMETER.get(format_parameter.lower())
        if hinted is not None:
            return hinted[1] if graph else hinted[0]
        if format_parameter in (GRAPH_TYPES if graph else RESULT_SET_TYPES):
            return format_parameter
    if graph:
        return negotiate(accept, list(GRAPH_TYPES), DEFAULT_GRAPH)
    available = list(RESULT_SET_TYPES)
    if query_kind == "ASK":
        available = [media for media in available if RESULT_SET_TYPES[media] in ("json", "xml")]
    return negotiate(accept, available, DEFAULT_RESULT_SET)


# ----- the worker process -----


def _framed(message: object) -> bytes:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    return struct.pack(">I", len(data)) + data


def _framed_write(stream: IO[bytes], message: object) -> None:
    stream.write(_framed(message))
    stream.flush()


def _framed_read(stream: IO[bytes]) -> Any:
    head = stream.read(4)
    if len(head) < 4:
        raise EOFError
    (size,) = struct.unpack(">I", head)
    data = stream.read(size)
    if len(data) < size:
        raise EOFError
    return pickle.loads(data)


LOAD_BATCH_TRIPLES = 10_000
"""Triples read into rdflib terms before they go into rdflib's memory store. Reading every
description first held all their terms at once beside the store: loading 20,000 descriptions
(30 MB of N-Triples) into Oxigraph that way peaked at 393 MB resident for a graph that then
held 217 MB."""


class _Worker:
    """Inside the child: the graph, the prepared queries, and the message loop."""

    def __init__(self, directory: Path, store: str, max_result_bytes: int) -> None:
        from rdflib import Graph
        from rdflib.plugins.sparql import prepareQuery

        self.directory = directory
        self.max_result_bytes = max_result_bytes
        # Oxigraph parses and evaluates a query itself, from its text.
        self.native = store == "oxigraph"
        self.graph = Graph(store="Oxigraph") if self.native else Graph()
        self.loaded: set[str] = set()
        self.applications = prepareQuery(APPLICATIONS_QUERY)
        for text in WARM_QUERIES[1:]:
            prepareQuery(text)
        self.load(sorted(path.stem for path in directory.glob("*.nt")))

    def load(self, cids: Sequence[str]) -> None:
        """Add the descriptions not loaded yet. Oxigraph parses their N-Triples itself, ten
        times faster than reading each into rdflib terms first (5,000 descriptions in 0.5 s
        against 5.2 s): the files are the service's own, written once validated, and each is
        checked against its CID, so they need no second validation here."""
        from robocloud.semantic import SemanticError, parse_canonical

        quads: list[Any] = []
        for cid in cids:
            if cid in self.loaded:
                continue
            data = self._verified(cid)
            if data is None:
                continue
            try:
                if self.native:
                    self.graph.parse(data=data, format="ox-nt")
                else:
                    quads.extend((s, p, o, self.graph) for s, p, o in parse_canonical(data).graph)
            except (SyntaxError, SemanticError) as exc:
                print(f"sparql worker: skipping {cid}: {exc}", file=sys.stderr)
                continue
            self.loaded.add(cid)
            if len(quads) >= LOAD_BATCH_TRIPLES:
                self.graph.addN(quads)
                quads.clear()
        self.graph.addN(quads)

    def _verified(self, cid: str) -> bytes | None:
        """The description file's bytes, or None when it cannot be read or holds other bytes
        than its CID names."""
        from robocloud.unixfs import import_bytes

        path = self.directory / f"{cid}.nt"
        try:
            data = path.read_bytes()
        except OSError as exc:
            print(f"sparql worker: skipping {path}: {exc}", file=sys.stderr)
            return None
        if str(import_bytes(data)[1]) != cid:
            print(f"sparql worker: skipping {path}: its bytes have another CID", file=sys.stderr)
            return None
        return data

    def query(self, text: str, accept: str | None, format_parameter: str | None) -> Any:
        from rdflib import Graph
        from rdflib.plugins.sparql.parser import parseQuery, parseUpdate

        try:
            parsed = parseQuery(text)
        except Exception as exc:  # pyparsing's errors and RecursionError for hostile nesting
            try:
                update = parseUpdate(text)
            except Exception:
                return ("error", "QuerySyntaxError", f"not a SPARQL 1.1 query: {exc}"[:1000])
            if "request" not in update:  # empty text, comments, prefixes: an empty update
                return ("error", "QuerySyntaxError", "not a SPARQL 1.1 query: it holds no query")
            return (
                "error",
                "UpdateRejectedError",
                "this endpoint answers queries only: SPARQL updates are rejected",
            )
        refused = _lexical_hazard(text) or _outside_reach(parsed)
        if refused is not None:
            return ("error", "QueryRefusedError", refused)
        kind = parsed[1].name.removesuffix("Query").upper()
        try:
            media_type = choose_format(kind, accept, format_parameter)
        except NotAcceptableError as exc:
            return ("not_acceptable", exc.accept, exc.available)
        from rdflib.plugins.sparql.algebra import translateQuery

        result = self.graph.query(text if self.native else translateQuery(parsed))
        body: bytes | None
        if kind in ("CONSTRUCT", "DESCRIBE"):
            assert result.graph is not None
            from robocloud.semantic import PREFIXES

            graph = Graph()
            for prefix, namespace in PREFIXES.items():
                graph.bind(prefix, namespace)
            graph.addN((s, p, _simple(o), graph) for s, p, o in result.graph)
            body = graph.serialize(format=GRAPH_TYPES[media_type], encoding="utf-8")
        else:
            if kind == "SELECT":
                result.bindings = [
                    {name: _simple(value) for name, value in row.items()} for row in result.bindings
                ]
            body = result.serialize(format=RESULT_SET_TYPES[media_type], encoding="utf-8")
        return ("ok", media_type, body or b"")

    def application_rows(self, consumes: str) -> Any:
        from rdflib import URIRef

        if self.native:
            # ``consumes`` is an IRI the service built from a checked media type or CID.
            bound = f"WHERE {{ VALUES ?consumes {{ <{consumes}> }}"
            rows = self.graph.query(APPLICATIONS_QUERY.replace("WHERE {", bound, 1))
        else:
            rows = self.graph.query(self.applications, initBindings={"consumes": URIRef(consumes)})
        fields = ("app", "name", "version", "direction", "port", "portName")
        optional = ("mediaType", "template", "attribute")
        answer = []
        for row in rows:
            values = row.asdict()  # type: ignore[union-attr]
            answer.append(
                tuple(str(values[name]) for name in fields)
                + tuple(str(values[name]) if name in values else None for name in optional)
            )
        return ("ok", answer)


_HAZARD = re.compile(r"\r(?!\n)|\\[uU][0-9A-Fa-f]")
"""A carriage return that no line feed follows, or a backslash-u escape."""


def _lexical_hazard(text: str) -> str | None:
    """Why the text is refused, if rdflib (whose parse ``_outside_reach`` checks) and Oxigraph
    (which parses the text again to run it) could read it as different tokens: the check is
    only as good as their agreement, and two disagreements hid SERVICE from it. rdflib ends a
    ``#`` comment at a line feed only, Oxigraph at a carriage return too, so in
    ``# \\r SERVICE <...> { } \\n`` Oxigraph ran what rdflib took for a comment. And rdflib
    expands ``\\u`` escapes over the whole text before parsing where Oxigraph expands them
    inside strings and IRIs only, so ``"a\\u005C" SERVICE ... '"'`` is one string to rdflib
    and a SERVICE call between two strings to Oxigraph. Without either, both read the same
    characters: whitespace and comments alike (a ``\\r\\n`` ends a comment for both), and
    strings and IRIs by the same grammar. Characters can be sent as themselves (UTF-8)
    instead of escaped. The worker's network filter (``_forbid_network``) stands behind this
    check for any disagreement not yet found."""
    found = _HAZARD.search(text)
    if found is None:
        return None
    what = "a carriage return not followed by a line feed" if found[0] == "\r" else "a \\u escape"
    return (
        f"{what} (at character {found.start()}) is refused: rdflib and Oxigraph read it "
        "differently, which could hide SERVICE from the check; send characters as themselves"
    )


def _outside_reach(parsed: Any) -> str | None:
    """Why the query is refused, if it asks the worker to fetch anything: ``SERVICE`` makes
    rdflib send HTTP requests wherever the query says, and ``FROM`` loads graphs from URLs."""
    from rdflib.plugins.sparql.parserutils import CompValue

    stack = [parsed]
    while stack:
        node = stack.pop()
        if isinstance(node, CompValue):
            if node.name == "ServiceGraphPattern":
                return "SERVICE is refused: the knowledge base answers from its own graph only"
            if node.name == "DatasetClause":
                return "FROM and FROM NAMED are refused: the knowledge base is one graph"
            stack.extend(node.values())
        elif isinstance(node, list | tuple) or hasattr(node, "asList"):
            stack.extend(list(node))
    return None


def _simple(term: Any) -> Any:
    """An ``xsd:string`` literal as the simple literal it is (RDF 1.1): Oxigraph gives every
    string its datatype, which rdflib would write out and compare as another term."""
    from rdflib import XSD, Literal

    if isinstance(term, Literal) and term.datatype == XSD.string:
        return Literal(str(term))
    return term


_SECCOMP_ABI = {"x86_64": (0xC000003E, 41), "aarch64": (0xC00000B7, 198)}
"""Per machine: Linux's AUDIT_ARCH value for its native ABI, and the number of socket(2)."""


class _SockFilter(ctypes.Structure):
    _fields_ = [
        ("code", ctypes.c_ushort),
        ("jt", ctypes.c_ubyte),
        ("jf", ctypes.c_ubyte),
        ("k", ctypes.c_uint32),
    ]


class _SockFprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.POINTER(_SockFilter))]


def _network_filter(arch: int, socket_call: int) -> list[tuple[int, int, int, int]]:
    """A seccomp program: ``socket(AF_INET or AF_INET6, ...)`` and every call made through
    another ABI than the machine's own (i386, x32) fail with EACCES; the rest goes through."""
    load, equal, answer = 0x20, 0x15, 0x06  # BPF_LD|BPF_W|BPF_ABS, BPF_JMP|BPF_JEQ|BPF_K, BPF_RET
    at_least = 0x35  # BPF_JMP|BPF_JGE|BPF_K
    allow, refuse = 0x7FFF0000, 0x00050000 | errno.EACCES  # SECCOMP_RET_ALLOW, _RET_ERRNO
    return [
        (load, 0, 0, 4),  # seccomp_data.arch
        (equal, 0, 7, arch),
        (load, 0, 0, 0),  # seccomp_data.nr
        (at_least, 5, 0, 0x40000000),  # x86-64's x32 calls, numbered from this bit
        (equal, 0, 3, socket_call),
        (load, 0, 0, 16),  # the low half of seccomp_data.args[0]: the address family
        (equal, 2, 0, socket.AF_INET),
        (equal, 1, 0, socket.AF_INET6),
        (answer, 0, 0, allow),
        (answer, 0, 0, refuse),
    ]


def _forbid_network() -> bool:
    """Make this process and the executors it forks unable to open an IP socket, so that no
    query can make it send a request, whatever a parser lets through: ``SERVICE`` is refused
    on rdflib's parse, but Oxigraph parses the text again and, given SERVICE, would POST to
    any address, internal ones included, with no switch in pyoxigraph to stop it. The worker
    reads descriptions from files and speaks to the service over pipes, so it needs no
    network. False where Linux's seccomp is not to be had (another system or machine)."""
    abi = _SECCOMP_ABI.get(platform.machine())
    if abi is None or not sys.platform.startswith("linux"):
        return False
    program = _network_filter(*abi)
    instructions = (_SockFilter * len(program))(*(_SockFilter(*step) for step in program))
    prog = _SockFprog(len(program), instructions)
    libc = ctypes.CDLL(None, use_errno=True)
    no_new_privs, set_seccomp, filter_mode = 38, 22, 2
    if libc.prctl(no_new_privs, 1, 0, 0, 0) != 0:
        return False
    return bool(libc.prctl(set_seccomp, filter_mode, ctypes.byref(prog), 0, 0) == 0)


def worker_main(argv: Sequence[str]) -> None:
    """``python -m services.storage.sparql DIRECTORY STORE MEMORY_BYTES MAX_RESULT_BYTES``."""
    die_with_parent()
    if not _forbid_network():
        print(
            "sparql worker: no seccomp here: queries are not kept off the network", file=sys.stderr
        )
    directory, store, memory, max_result = Path(argv[0]), argv[1], int(argv[2]), int(argv[3])
    limit_memory(memory)
    sys.setrecursionlimit(10_000)
    inbox, outbox = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing but framed answers may reach the parent's pipe
    import rdflib.plugins.sparql

    rdflib.plugins.sparql.SPARQL_LOAD_GRAPHS = False  # never fetch a graph a query names
    worker = _Worker(directory, store, max_result)
    _framed_write(outbox, ("ready", len(worker.loaded)))
    _relay(worker, inbox, outbox)


def _relay(worker: _Worker, inbox: IO[bytes], outbox: IO[bytes]) -> None:
    """The worker's loop: every message goes on to its executor, loads are also applied here
    (so a new executor starts with every description), and an answer comes back unless the
    service says ``stop`` first: then the executor is killed, a new one forked, and the answer
    is ``("stopped",)``. The service sends ``stop`` only while a query runs; one that crossed
    the query's answer finds nothing to stop. ``refresh`` forks a new executor in place of an
    idle one, and is answered ``("refreshed",)``."""
    executor = _Executor(worker, inbox, outbox)
    while True:
        try:
            message = _framed_read(inbox)
        except EOFError:
            executor.stop()
            return
        if message[0] == "stop":
            continue
        if message[0] == "load":
            worker.load(message[1])
            executor.send(message)
            continue
        if message[0] == "refresh":
            executor.stop()
            executor = _Executor(worker, inbox, outbox)
            _framed_write(outbox, ("refreshed",))
            continue
        executor.send(message)
        answer = executor.answer(inbox.fileno())
        if isinstance(answer, Interruption):
            executor.stop()
            executor = _Executor(worker, inbox, outbox)
            if answer is Interruption.STOPPED:
                _framed_read(inbox)
                answer = _framed(("stopped",))
            else:
                answer = _framed(("error", "WorkerFailedError", "the query's process died"))
        outbox.write(answer)
        outbox.flush()


class Interruption(enum.Enum):
    """Why an executor gave no answer: the service said stop, or the executor died."""

    STOPPED = "stopped"
    DIED = "died"


class _Executor:
    """A process forked from the worker that answers its messages in turn (``_serve``). It
    shares the worker's graph, so replacing one costs a fork (10 ms for a 180 MiB worker)
    where starting a worker costs a load of every description (seconds)."""

    def __init__(self, worker: _Worker, inbox: IO[bytes], outbox: IO[bytes]) -> None:
        to_child, requests = os.pipe()
        answers, from_child = os.pipe()
        pid = os.fork()
        if pid == 0:
            for fd in (requests, answers, inbox.fileno(), outbox.fileno()):
                os.close(fd)
            die_with_parent()
            with os.fdopen(to_child, "rb") as child_in, os.fdopen(from_child, "wb") as child_out:
                _serve(worker, child_in, child_out)
            os._exit(0)
        os.close(to_child)
        os.close(from_child)
        self.pid = pid
        self.requests = os.fdopen(requests, "wb")
        self.answers = answers

    def send(self, message: tuple[Any, ...]) -> None:
        _framed_write(self.requests, message)

    def answer(self, stop: int) -> bytes | Interruption:
        """The next framed answer, unless ``stop`` became readable first or the executor
        closed its pipe before a whole answer."""
        received = bytearray()
        while len(received) < 4 or len(received) < 4 + struct.unpack(">I", received[:4])[0]:
            if stop in select.select([self.answers, stop], [], [])[0]:
                return Interruption.STOPPED
            chunk = os.read(self.answers, 1 << 20)
            if not chunk:
                return Interruption.DIED
            received += chunk
        return bytes(received)

    def stop(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.pid, signal.SIGKILL)
        os.waitpid(self.pid, 0)
        self.requests.close()
        os.close(self.answers)


def _serve(worker: _Worker, inbox: IO[bytes], outbox: IO[bytes]) -> None:
    """The executor's loop: apply each load, answer each query, until the pipe closes.

    An answer over the result limit is refused here, not sent: the service reads no more
    than the limit off the pipe, so it could only replace a worker that sent one (a reload of
    the whole graph, seconds of a core, for a query anyone can write)."""
    while True:
        try:
            message = _framed_read(inbox)
        except EOFError:
            return
        if message[0] == "load":
            worker.load(message[1])
            continue
        answer = _framed(_answer(worker, message))
        if len(answer) - 4 > worker.max_result_bytes + ANSWER_OVERHEAD_BYTES:
            answer = _framed(("error", "ResultTooLargeError", str(worker.max_result_bytes)))
        outbox.write(answer)
        outbox.flush()


def _answer(worker: _Worker, message: tuple[Any, ...]) -> Any:
    """The answer to one message, a failure of the query included."""
    try:
        if message[0] == "query":
            return worker.query(message[1], message[2], message[3])
        if message[0] == "applications":
            return worker.application_rows(message[1])
        return ("error", "WorkerFailedError", f"unknown message {message[0]!r}")
    except MemoryError:
        return ("error", "WorkerFailedError", "the query ran out of memory")
    except RecursionError:
        return ("error", "QuerySyntaxError", "the query nests too deeply")
    except Exception as exc:  # a query that rdflib cannot evaluate (type errors, ...)
        return ("error", "QueryFailedError", f"{type(exc).__name__}: {exc}"[:1000])


# ----- the pool, in the service's process -----


class QueryFailedError(SparqlError):
    """rdflib could not evaluate the query (an error in the query, not in the service)."""


_ERRORS: dict[str, Callable[[str], SparqlError]] = {
    "QuerySyntaxError": QuerySyntaxError,
    "UpdateRejectedError": UpdateRejectedError,
    "QueryFailedError": QueryFailedError,
    "QueryRefusedError": QueryRefusedError,
    "WorkerFailedError": WorkerFailedError,
    "ResultTooLargeError": lambda limit: ResultTooLargeError(int(limit)),
}


ANSWER_OVERHEAD_BYTES = 4096
"""What an answer may hold beyond the result's own bytes (its framing and media type)."""
STOP_WAIT_S = 5.0
"""How long a worker may take to stop a query's process (or fork a fresh one) and say so
before it is replaced."""
IDLE_REFRESH_S = 30.0
"""How long a worker stays idle after a query before its executor is forked afresh."""
SPAWN_RETRY_S = 0.5
"""How long after a failed start of a worker (a fork refused: EAGAIN, ENOMEM) it is tried
again; doubled after each further failure, up to ``SPAWN_RETRY_MAX_S``."""
SPAWN_RETRY_MAX_S = 30.0
START_RETRY_S = 1.0
"""How long after a worker died before it was ready it is replaced; doubled after each further
one in a row, up to ``START_RETRY_MAX_S``. A graph larger than the workers' memory ends every
worker while it loads: replaced after a second each, two workers loading in turn held both
cores of a development machine for good."""
START_RETRY_MAX_S = 60.0


class _StalledWrite(Exception):
    """The worker did not take a whole message off its pipe before the deadline: it is hung
    (stopped, or stuck in the kernel), and a message half written cannot be taken back."""


@dataclass
class _Child:
    process: subprocess.Popen[bytes]
    pending: list[str]
    ready: bool = False
    last_query: float | None = None
    """When its executor last answered; None while it has answered nothing."""


class SparqlWorkers:
    """A pool of worker processes answering queries over the description files in ``directory``.

    ``add`` makes new descriptions visible to every later query; ``query`` and
    ``applications`` block the calling thread (run them off the event loop) for at most
    ``timeout_s``, waiting for a free worker included.
    """

    def __init__(
        self,
        directory: Path,
        *,
        workers: int,
        timeout_s: float,
        max_result_bytes: int,
        memory_bytes: int,
        store: str = "memory",
        start_timeout_s: float = 300.0,
        idle_refresh_s: float = IDLE_REFRESH_S,
    ) -> None:
        self.directory = directory
        self.count = workers
        self.timeout_s = timeout_s
        self.max_result_bytes = max_result_bytes
        self.memory_bytes = memory_bytes
        self.store = store
        self.start_timeout_s = start_timeout_s
        self.idle_refresh_s = idle_refresh_s
        self._lock = threading.Lock()
        self._children: list[_Child] = []
        self._idle: queue.Queue[_Child] = queue.Queue()
        self._closed = False
        self._loaded = False
        self.replaced = 0
        self.stopped = 0
        self.refreshed = 0
        self.start_failures = 0
        """Workers in a row that died before they were ready."""
        self._closing = threading.Event()
        self._starting = 0
        """Workers being started (between their fork and their registration)."""
        self._short = threading.Event()
        """Set when a worker could not be started: ``_keep_count`` starts it again."""

    def start(self) -> None:
        """Start every worker in the background; each becomes idle once it has loaded."""
        self._short.set()
        threading.Thread(target=self._keep_count, daemon=True).start()
        threading.Thread(target=self._refresh_idle, daemon=True).start()

    def loaded(self) -> bool:
        """Whether a worker has loaded the graph, ever, and a worker lives (or is starting):
        the knowledge base answers queries from then on. A worker replaced later (a query past
        its time is stopped by killing its worker) does not undo it: while every worker
        reloads, queries get 503 ``knowledge_loading``; readiness flapped with each
        replacement a slow query caused. A pool left with no worker at all (every fork
        refused) is not ready until one is started again."""
        with self._lock:
            return self._loaded and bool(self._children or self._starting)

    def describe(self) -> dict[str, int]:
        with self._lock:
            ready = sum(child.ready for child in self._children)
        idle = self._idle.qsize()
        return {
            "ready": ready,
            "busy": max(ready - idle, 0),
            "replaced": self.replaced,
            "stopped": self.stopped,
            "refreshed": self.refreshed,
            "start_failures": self.start_failures,
        }

    def add(self, cids: Sequence[str]) -> None:
        with self._lock:
            for child in self._children:
                child.pending.extend(cids)

    def close(self) -> None:
        self._closing.set()
        self._short.set()
        with self._lock:
            self._closed = True
            children = list(self._children)
            self._children.clear()
        for child in children:
            self._stop(child)

    def query(
        self, text: str, accept: str | None, format_parameter: str | None = None
    ) -> tuple[str, bytes]:
        """The answer's media type and bytes."""
        answer = self._ask(("query", text, accept, format_parameter))
        if answer[0] == "not_acceptable":
            raise NotAcceptableError(answer[1], answer[2])
        return answer[1], answer[2]

    def application_rows(self, consumes: str) -> list[tuple[str | None, ...]]:
        rows: list[tuple[str | None, ...]] = self._ask(("applications", consumes))[1]
        return rows

    def _ask(self, message: tuple[Any, ...]) -> Any:
        deadline = time.monotonic() + self.timeout_s
        with self._lock:
            if not any(child.ready for child in self._children):
                raise WorkersUnavailableError("the query workers are still loading the graph")
        try:
            child = self._idle.get(timeout=self.timeout_s)
        except queue.Empty:
            raise QueryTimeoutError(self.timeout_s, waiting=True) from None
        try:
            with self._lock:
                pending, child.pending = child.pending, []
            if pending:
                self._send(child, ("load", pending), deadline)
            self._send(child, message, deadline)
            answer = self._read_answer(child, deadline)
            child.last_query = time.monotonic()
        except _StalledWrite:
            self._replace(child, "did not take the query off its pipe in time")
            raise QueryTimeoutError(self.timeout_s) from None
        except QueryTimeoutError:
            if self._stop_query(child):
                child.last_query = None  # the executor is a fresh one
                self._idle.put(child)
            else:
                self._replace(child, "timed out")
            raise
        except (OSError, EOFError, ValueError, pickle.UnpicklingError) as exc:
            self._replace(child, f"failed: {exc}")
            raise WorkerFailedError(f"the query worker failed ({exc}); it was replaced") from None
        except ResultTooLargeError:  # the worker should have refused it itself
            self._replace(child, "answered too much")
            raise
        self._idle.put(child)
        if answer[0] == "error":
            raise _ERRORS.get(answer[1], WorkerFailedError)(answer[2])
        return answer

    def _stop_query(self, child: _Child) -> bool:
        """Have the worker kill the executor running the query (and fork a new one); whether
        it confirmed (or answered, the query having finished meanwhile) within
        ``STOP_WAIT_S``."""
        deadline = time.monotonic() + STOP_WAIT_S
        try:
            self._send(child, ("stop",), deadline)
            self._read_answer(child, deadline)
        except (_StalledWrite, SparqlError, OSError, EOFError, ValueError, pickle.UnpicklingError):
            return False
        with self._lock:
            self.stopped += 1
        return True

    def _refresh_idle(self) -> None:
        """Every so often, take each idle worker in turn and, when it has been idle for
        ``idle_refresh_s`` since a query, have it fork a fresh executor."""
        while not self._closing.wait(self.idle_refresh_s / 4):
            try:
                self._refresh_idle_once()
            except Exception:  # the thread must outlive one bad turn
                log.exception("refreshing the idle SPARQL workers failed")

    def _refresh_idle_once(self) -> None:
        for _ in range(self._idle.qsize()):
            try:
                child = self._idle.get_nowait()
            except queue.Empty:
                break
            idle_since = child.last_query
            if idle_since is None or time.monotonic() - idle_since < self.idle_refresh_s:
                self._idle.put(child)
            elif self._refresh(child):
                child.last_query = None
                self._idle.put(child)
            else:
                self._replace(child, "did not refresh its executor")

    def _refresh(self, child: _Child) -> bool:
        """Have the worker fork a fresh executor; whether it said so within ``STOP_WAIT_S``."""
        deadline = time.monotonic() + STOP_WAIT_S
        try:
            self._send(child, ("refresh",), deadline)
            answer = self._read_answer(child, deadline)
        except (_StalledWrite, SparqlError, OSError, EOFError, ValueError, pickle.UnpicklingError):
            return False
        if answer != ("refreshed",):
            return False
        with self._lock:
            self.refreshed += 1
        return True

    @staticmethod
    def _send(child: _Child, message: object, deadline: float) -> None:
        """Write one framed message to the worker by ``deadline``: its pipe holds 64 KiB, and
        a worker that is stopped or stuck takes nothing off it, so a blocking write of a query
        near its maximum size (or of many pending loads) would wait for good. The pipe is
        non-blocking on this side (``_spawn``)."""
        stdin = child.process.stdin
        assert stdin is not None
        fd = stdin.fileno()
        data = memoryview(_framed(message))
        while data:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([], [fd], [], remaining)[1]:
                raise _StalledWrite
            try:
                written = os.write(fd, data)
            except BlockingIOError:
                continue
            data = data[written:]

    def _read_answer(self, child: _Child, deadline: float) -> Any:
        stdout = child.process.stdout
        assert stdout is not None
        fd = stdout.fileno()
        head = self._read_exact(fd, 4, deadline)
        (size,) = struct.unpack(">I", head)
        if size > self.max_result_bytes + ANSWER_OVERHEAD_BYTES:
            raise ResultTooLargeError(self.max_result_bytes)
        return pickle.loads(self._read_exact(fd, size, deadline))

    def _read_exact(self, fd: int, size: int, deadline: float) -> bytes:
        chunks: list[bytes] = []
        while size:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([fd], [], [], remaining)[0]:
                raise QueryTimeoutError(self.timeout_s)
            chunk = os.read(fd, min(size, 1 << 20))
            if not chunk:
                raise EOFError("the worker closed its pipe")
            chunks.append(chunk)
            size -= len(chunk)
        return b"".join(chunks)

    def _spawn(self) -> None:
        """Start one worker; registered before it lists the files, so no addition is missed.
        Raises what the fork raised (EAGAIN, ENOMEM)."""
        with self._lock:
            if self._closed:
                return
            self._starting += 1
        try:
            process = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "services.storage.sparql",
                    str(self.directory),
                    self.store,
                    str(self.memory_bytes),
                    str(self.max_result_bytes),
                ],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                cwd=Path(__file__).resolve().parents[2],
            )
        except BaseException:
            with self._lock:
                self._starting -= 1
            raise
        assert process.stdin is not None
        os.set_blocking(process.stdin.fileno(), False)  # written only through ``_send``
        child = _Child(process, [])
        with self._lock:
            self._starting -= 1
            if self._closed:
                self._stop(child)
                return
            self._children.append(child)
        try:
            threading.Thread(target=self._await_ready, args=(child,), daemon=True).start()
        except BaseException:
            with self._lock:
                self._children.remove(child)
            self._stop(child)
            raise

    def _keep_count(self) -> None:
        """The one thread that starts workers: at start, and whenever the pool is short of its
        ``count`` (a worker replaced, a fork refused), again with backoff while forks fail.

        A worker dies with the thread that forked it (``die_with_parent``: Linux's parent
        death signal follows the forking *thread*), so no other thread may fork one. A
        replacement forked on a request's thread was killed when that thread ended (anyio
        ends an idle one after 10 s), and the next query to it failed and replaced it again,
        reloading every description; one forked by ``_await_ready`` died with it."""
        delay = SPAWN_RETRY_S
        while True:
            self._short.wait()
            if self._closing.is_set():
                return
            self._short.clear()  # before counting: a failure after the count sets it again
            with self._lock:
                missing = self.count - len(self._children) - self._starting
            try:
                for _ in range(missing):
                    self._spawn()
            except Exception as exc:
                log.error("a SPARQL worker could not be started (%s): again in %g s", exc, delay)
                if self._closing.wait(delay):
                    return
                delay = min(delay * 2, SPAWN_RETRY_MAX_S)
                self._short.set()
            else:
                delay = SPAWN_RETRY_S

    def _await_ready(self, child: _Child) -> None:
        try:
            self._await_ready_once(child)
        except Exception:  # a thread that dies here would leave its worker never ready
            log.exception("waiting for SPARQL worker %d failed", child.process.pid)
            self._replace(child, "could not be awaited")

    def _await_ready_once(self, child: _Child) -> None:
        stdout = child.process.stdout
        assert stdout is not None
        try:
            deadline = time.monotonic() + self.start_timeout_s
            answer = pickle.loads(
                self._read_exact(
                    stdout.fileno(),
                    struct.unpack(">I", self._read_exact(stdout.fileno(), 4, deadline))[0],
                    deadline,
                )
            )
            if answer[0] != "ready":
                raise EOFError(f"the worker said {answer!r}")
        except (SparqlError, OSError, EOFError, ValueError, pickle.UnpicklingError) as exc:
            with self._lock:
                self.start_failures += 1
                failures = self.start_failures
            delay = min(START_RETRY_S * 2 ** min(failures - 1, 16), START_RETRY_MAX_S)
            log.error(
                "a SPARQL worker did not start (%d in a row, replaced in %g s): %s; a graph "
                "larger than ROBOCLOUD_KNOWLEDGE_WORKER_MEMORY_BYTES allows ends each one",
                failures,
                delay,
                exc,
            )
            self._closing.wait(delay)
            self._replace(child, "did not start")
            return
        with self._lock:
            child.ready = True
            self._loaded = True
            self.start_failures = 0
        log.info("SPARQL worker %d ready with %d descriptions", child.process.pid, answer[1])
        self._idle.put(child)

    def _replace(self, child: _Child, why: str) -> None:
        log.warning("SPARQL worker %d %s: replacing it", child.process.pid, why)
        self._stop(child)
        with self._lock:
            if child in self._children:
                self._children.remove(child)
            closed = self._closed
            self.replaced += 1
        if not closed:
            self._short.set()

    @staticmethod
    def _stop(child: _Child) -> None:
        if child.process.poll() is None:
            child.process.kill()
        child.process.wait()
        for stream in (child.process.stdin, child.process.stdout):
            if stream is not None:
                with contextlib.suppress(OSError):
                    stream.close()


if __name__ == "__main__":
    worker_main(sys.argv[1:])
