"""Routes of the knowledge base (engineer semantic): descriptions added by CID, SPARQL 1.1
Protocol queries answered by worker processes, and the applications index; with the knowledge
base's opening and its running life beside the app.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager, contextmanager
from typing import Any
from urllib.parse import parse_qsl

import anyio
from fastapi import APIRouter, FastAPI, Query, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from robocloud.cas import Cas
from robocloud.ledger import LedgerService
from services.common.auth import SignedAddress
from services.common.bodies import media_type, read_json
from services.common.errors import BadRequest, UnsupportedMediaType
from services.common.slots import Slots
from services.storage.knowledge import KnowledgeBase
from services.storage.settings import StorageSettings
from services.storage.sparql import QueryTooLargeError, SparqlWorkers, UpdateRejectedError

SPARQL_PATH = "/v1/knowledge/sparql"
"""A read: unsigned for POST too, so that any SPARQL 1.1 Protocol client can ask."""


class KnowledgeRequest(BaseModel):
    cid: str = Field(description="the CID of a description in canonical form, stored in cas")


def _knowledge(request: Request) -> KnowledgeBase:
    knowledge: KnowledgeBase = request.app.state.knowledge
    return knowledge


def _sparql_answer(media: str, body: bytes) -> Response:
    charset = "" if media.endswith("+xml") or media.endswith("/xml") else "; charset=utf-8"
    return Response(body, media_type=f"{media}{charset}", headers={"Vary": "Accept"})


def knowledge_router(settings: StorageSettings) -> APIRouter:
    router = APIRouter(tags=["knowledge"])
    # One turn per worker process: a query waiting for a free worker waits on the event loop,
    # not on one of the threads every other route needs.
    worker_turns = Slots("SPARQL", settings.knowledge_workers, settings.knowledge_query_timeout_s)

    async def run_query(
        request: Request, query: str | None, update: str | None, format_hint: str | None
    ) -> Response:
        if update is not None:
            raise UpdateRejectedError("this endpoint answers queries only: updates are rejected")
        if query is None:
            raise BadRequest(
                "the query parameter is required",
                code="missing_parameter",
                details={"field": "query"},
            )
        size = len(query.encode())
        if size > settings.knowledge_max_query_bytes:
            raise QueryTooLargeError(size, settings.knowledge_max_query_bytes)
        accept = request.headers.get("accept")
        workers = _knowledge(request).workers
        media, body = await worker_turns.run_sync(lambda: workers.query(query, accept, format_hint))
        return _sparql_answer(media, body)

    def dataset_refused(parameters: list[tuple[str, str]]) -> None:
        for name, _ in parameters:
            if name in ("default-graph-uri", "named-graph-uri", "using-graph-uri"):
                raise BadRequest(
                    f"{name} is not supported: the knowledge base is one graph",
                    code="unsupported_parameter",
                    details={"field": name},
                )

    def one(parameters: list[tuple[str, str]], name: str) -> str | None:
        values = [value for key, value in parameters if key == name]
        if len(values) > 1:
            raise BadRequest(
                f"{name} is given {len(values)} times",
                code="invalid_parameter",
                details={"field": name},
            )
        return values[0] if values else None

    def format_hint(parameters: list[tuple[str, str]]) -> str | None:
        return one(parameters, "format") or one(parameters, "output")

    @router.post("/v1/knowledge")
    async def add_description(request: Request, signer: SignedAddress) -> dict[str, Any]:
        """Fetch a description from cas by CID, validate it against its shapes and index it;
        a new one counts towards its signer's share."""
        body = await read_json(request, KnowledgeRequest)
        assert body is not None
        knowledge = _knowledge(request)
        indexed = await anyio.to_thread.run_sync(lambda: knowledge.add(body.cid, robot=signer))
        return indexed.as_dict()

    @router.get("/v1/knowledge")
    async def knowledge_state(request: Request) -> dict[str, Any]:
        """How many descriptions are indexed, and where the ledger follower is. Read on a
        worker thread: the knowledge base's lock is held across the fsyncs of each
        description stored."""
        knowledge = _knowledge(request)

        def state() -> dict[str, Any]:
            return {
                "descriptions": len(knowledge),
                "bytes": knowledge.total_bytes,
                "max_bytes": settings.knowledge_max_total_bytes,
                "max_bytes_per_robot": settings.knowledge_max_bytes_per_robot,
                "store": settings.knowledge_store,
                "workers": knowledge.workers.describe(),
                "ledger": knowledge.follow_state(),
            }

        return await anyio.to_thread.run_sync(state)

    @router.get(SPARQL_PATH)
    async def sparql_get(request: Request) -> Response:
        """SPARQL 1.1 Protocol query via GET (``?query=``); answers by content negotiation."""
        parameters = list(request.query_params.multi_items())
        dataset_refused(parameters)
        return await run_query(
            request, one(parameters, "query"), one(parameters, "update"), format_hint(parameters)
        )

    @router.post(SPARQL_PATH)
    async def sparql_post(request: Request) -> Response:
        """SPARQL 1.1 Protocol query via POST: a form (``query=``) or ``application/sparql-query``.

        Updates (``update=`` or ``application/sparql-update``) are rejected.
        """
        kind = media_type(request)
        raw = await request.body()
        parameters = list(request.query_params.multi_items())
        if kind == "application/sparql-update":
            raise UpdateRejectedError("this endpoint answers queries only: updates are rejected")
        if kind == "application/sparql-query":
            query: str | None = raw.decode("utf-8", errors="replace")
        elif kind == "application/x-www-form-urlencoded":
            parameters += _form_fields(raw)
            query = one(parameters, "query")
        else:
            raise UnsupportedMediaType(
                "a SPARQL query is sent as application/x-www-form-urlencoded or "
                "application/sparql-query",
                details={"header": "Content-Type", "received": kind},
            )
        dataset_refused(parameters)
        return await run_query(request, query, one(parameters, "update"), format_hint(parameters))

    @router.get("/v1/knowledge/applications")
    async def applications(
        request: Request,
        consumes: str = Query(
            description="a media type (image/jpeg), its IANA IRI, or a template's ipfs://<cid>"
        ),
        produces: str | None = Query(default=None, description="the same, for an output"),
        limit: int = Query(default=100, ge=1, le=1000),
    ) -> dict[str, Any]:
        """Applications with an input of type ``consumes`` (and an output of ``produces``)."""
        knowledge = _knowledge(request)
        found = await worker_turns.run_sync(
            lambda: knowledge.applications(consumes, produces, limit)
        )
        return {"applications": found}

    return router


FORM_FIELDS_BYTES = 4096
"""Room in a SPARQL form for the fields beside its query (format, output)."""


def sparql_body_limit(settings: StorageSettings) -> int:
    """The most a SPARQL POST's body may hold: its query at the most a query may hold, each
    byte percent-encoded (three) in a form, and the other fields. It was the service's
    default of 16 MiB, which anyone could send, unsigned, for the form to be parsed on the
    event loop (0.8 s a 4 MiB form of escapes) before its query was found too large."""
    return 3 * settings.knowledge_max_query_bytes + FORM_FIELDS_BYTES


MAX_FORM_FIELDS = 32
"""Fields a SPARQL query form may hold: the protocol names a handful (query, format or
output, the graph URIs, which are refused), so this leaves room and bounds the parse."""


def _form_fields(raw: bytes) -> list[tuple[str, str]]:
    """A form body's fields; past :data:`MAX_FORM_FIELDS`, 400 ``invalid_parameter`` naming
    how many it holds: ``parse_qsl`` raises ValueError there, which answered 500."""
    text = raw.decode("utf-8", errors="replace")
    try:
        return parse_qsl(text, max_num_fields=MAX_FORM_FIELDS)
    except ValueError:
        fields = text.count("&") + 1  # as parse_qsl counts them
        raise BadRequest(
            f"the form holds {fields} fields, more than the {MAX_FORM_FIELDS} it may",
            code="invalid_parameter",
            details={"field": "body", "fields": fields, "limit": MAX_FORM_FIELDS},
        ) from None


def open_knowledge(settings: StorageSettings) -> KnowledgeBase:
    """The knowledge base over the node's data directory; its workers start with the app."""
    root = settings.resolved_data_dir() / "knowledge"
    workers = SparqlWorkers(
        root / "descriptions",
        workers=settings.knowledge_workers,
        timeout_s=settings.knowledge_query_timeout_s,
        max_result_bytes=settings.knowledge_max_result_bytes,
        memory_bytes=settings.knowledge_worker_memory_bytes,
        store=settings.knowledge_store,
    )

    @contextmanager
    def connect_cas() -> Iterator[Cas]:
        with Cas(settings.cas_url) as cas:
            yield cas

    return KnowledgeBase(
        root,
        workers,
        connect_cas,
        max_total_bytes=settings.knowledge_max_total_bytes,
        max_bytes_per_robot=settings.knowledge_max_bytes_per_robot,
    )


@asynccontextmanager
async def knowledge_running(app: FastAPI, settings: StorageSettings) -> AsyncIterator[None]:
    """The app's knowledge base at work: its SPARQL workers, and the ledger follower that
    indexes advertised descriptions, stopped when the app stops."""
    knowledge: KnowledgeBase = app.state.knowledge
    knowledge.workers.start()
    if settings.knowledge_follow_ledger:

        @contextmanager
        def connect_ledger() -> Iterator[LedgerService]:
            with LedgerService(settings.ledger_url) as ledger:
                yield ledger

        knowledge.follow(connect_ledger, settings.knowledge_poll_s, settings.knowledge_wait_s)
    try:
        yield
    finally:
        await anyio.to_thread.run_sync(knowledge.close)
        await anyio.to_thread.run_sync(knowledge.workers.close)
