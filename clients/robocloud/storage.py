"""``Storage``: templates, records and queries of the storage service, as a robot uses them.

Records are checked against their template here before they are sent (the same
``robocloud.templates`` code the service runs), so a robot learns of a malformed record
without a round trip, and batches go as NDJSON. Answers are parsed with the SDK's nesting
bound and checked for the shape this client relies on.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeGuard
from urllib.parse import quote

from robocloud import jcs
from robocloud.client import ServiceClient
from robocloud.errors import ConflictError, InvalidAnswerError
from robocloud.proofs import EthCall, RecordId, RecordProof, rpc_chain_id, verify_record_proof
from robocloud.templates import Template, parse_template, parse_template_id, validate_record

NDJSON = "application/x-ndjson"
MAX_LISTED = 100_000
"""The most template versions ``Storage.templates`` lists: a catalog that goes on past it is
a service inventing pages, and a robot's memory is not its to fill."""
MAX_PAGES = 1_000
"""The most pages ``Storage.templates`` follows (100,000 versions at the default limit)."""


@dataclass(frozen=True)
class TemplateVersion:
    """A template version as the catalog holds it."""

    template: Template
    status: str
    author: str
    reviewer: str | None
    reason: str | None

    @property
    def id(self) -> str:
        return self.template.id


@dataclass(frozen=True)
class StoredRecord:
    id: str
    record: dict[str, Any]
    signer: str | None
    meta: dict[str, Any] | None = None


@dataclass(frozen=True)
class RecordPage:
    records: list[StoredRecord]
    next: str | None
    keywords_pending: int


@dataclass(frozen=True)
class Interval:
    """A time one robot's field held a value: entered at ``enter``, left at ``exit`` (None
    while it still holds). The service builds these and robots read them, one wire form."""

    robot: str
    enter: int
    exit: int | None

    def to_json(self) -> dict[str, Any]:
        return {"robot": self.robot, "enter": self.enter, "exit": self.exit}

    @classmethod
    def from_json(cls, item: Any) -> Interval:
        """The interval an answer holds; ``ValueError`` naming the field that is malformed.

        Exact types, no coercion: ``int("12")`` or ``int(True)`` would turn an answer that
        is wrong into a time the robot then believes."""
        if not isinstance(item, dict):
            raise ValueError(f"an interval must be an object, not {type(item).__name__}")
        robot, enter, exit_ns = item.get("robot"), item.get("enter"), item.get("exit")
        if not isinstance(robot, str):
            raise ValueError(f"an interval's robot must be text, not {robot!r:.80}")
        if not _is_time(enter):
            raise ValueError(f"an interval's enter must be an integer time, not {enter!r:.80}")
        if exit_ns is not None and not _is_time(exit_ns):
            raise ValueError(
                f"an interval's exit must be an integer time or null, not {exit_ns!r:.80}"
            )
        return cls(robot, enter, exit_ns)


ANCHOR_POLL_S = 0.1
"""The first pause before asking again for a proof not anchored yet; it doubles up to 1 s."""


class Storage(ServiceClient):
    """The storage service: templates, records, queries and intervals."""

    default_service = "storage"

    def _version(self, answer: Any) -> TemplateVersion:
        try:
            template = parse_template(
                {key: answer[key] for key in ("name", "version", "fields", "description")}
            )
            return TemplateVersion(
                template,
                str(answer["status"]),
                str(answer["author"]),
                _optional_text(answer, "reviewer"),
                _optional_text(answer, "reason"),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidAnswerError(
                f"the storage service sent an invalid template: {exc}"
            ) from exc

    def create_template(self, document: Mapping[str, Any]) -> TemplateVersion:
        return self._version(self.post_json("/v1/templates", dict(document)))

    def new_version(self, name: str, document: Mapping[str, Any]) -> TemplateVersion:
        path = f"/v1/templates/{quote(name, safe='')}/versions"
        return self._version(self.post_json(path, dict(document)))

    def edit_template(self, template_id: str, document: Mapping[str, Any]) -> TemplateVersion:
        parse_template_id(template_id)
        answer = self.request("PUT", f"/v1/templates/{template_id}", json=dict(document))
        return self._version_of(template_id, self.json_of(answer))

    def submit_template(self, template_id: str) -> TemplateVersion:
        parse_template_id(template_id)
        return self._version_of(template_id, self.post_json(f"/v1/templates/{template_id}/submit"))

    def review_template(
        self, template_id: str, decision: str, reason: str | None = None
    ) -> TemplateVersion:
        parse_template_id(template_id)
        body: dict[str, Any] = {"decision": decision}
        if reason is not None:
            body["reason"] = reason
        return self._version_of(
            template_id, self.post_json(f"/v1/templates/{template_id}/review", body)
        )

    def template(self, template_id: str) -> TemplateVersion:
        parse_template_id(template_id)
        return self._version_of(template_id, self.get_json(f"/v1/templates/{template_id}"))

    def _version_of(self, template_id: str, answer: Any) -> TemplateVersion:
        """The version ``answer`` holds, which must be ``template_id``'s."""
        version = self._version(answer)
        _check_answered("template", template_id, version.id)
        return version

    def templates(
        self,
        *,
        name: str | None = None,
        status: str | None = None,
        limit: int = 100,
        max_items: int = MAX_LISTED,
    ) -> Iterator[TemplateVersion]:
        """Every version (filtered), following the service's pages.

        A list that would not end is an ``InvalidAnswerError``: a ``next`` cursor answered
        twice, a page larger than ``limit`` (or empty, yet with a ``next``), more than
        ``max_items`` versions or ``MAX_PAGES`` pages.
        """
        after: str | None = None
        seen: set[str] = set()
        listed = 0
        for _ in range(MAX_PAGES):
            page, after = self._template_page(name, status, after, limit)
            listed += len(page)
            if listed > max_items:
                raise InvalidAnswerError(
                    f"the storage service lists more than {max_items} template versions"
                )
            yield from page
            if after is None:
                return
            if after in seen:
                raise InvalidAnswerError(
                    f"the storage service's template list repeats its page {after[:80]!r}"
                )
            seen.add(after)
        raise InvalidAnswerError(f"the storage service's template list runs past {MAX_PAGES} pages")

    def _template_page(
        self, name: str | None, status: str | None, after: str | None, limit: int
    ) -> tuple[list[TemplateVersion], str | None]:
        """One page of the catalog and the cursor of the next (None at the end)."""
        params = {"name": name, "status": status, "after": after, "limit": limit}
        answer = self.get_json(
            "/v1/templates", params={k: v for k, v in params.items() if v is not None}
        )
        if not isinstance(answer, dict) or not isinstance(answer.get("templates"), list):
            raise InvalidAnswerError("the storage service sent an invalid template list")
        items, following = answer["templates"], answer.get("next")
        following = following if isinstance(following, str) else None
        if len(items) > limit or (following is not None and not items):
            raise InvalidAnswerError(
                f"asked for pages of {limit} template versions, the storage service sent "
                f"{len(items)}{' and more to come' if following is not None else ''}"
            )
        return [self._version(item) for item in items], following

    def append(
        self,
        records: Sequence[Mapping[str, Any]],
        *,
        templates: Mapping[str, Template] | None = None,
    ) -> list[str]:
        """Store records (all or none) and return their ids.

        Records whose template is in ``templates`` are validated here first, raising
        ``RecordInvalid`` with the field path before anything is sent.
        """
        lines = []
        for record in records:
            template = (templates or {}).get(str(record.get("template")))
            if template is not None:
                validate_record(template, record)
            lines.append(jcs.canonical(dict(record)))
        body = b"\n".join(lines) + b"\n"
        answer = self.json_of(
            self.request("POST", "/v1/records", content=body, headers={"Content-Type": NDJSON})
        )
        ids = answer.get("ids") if isinstance(answer, dict) else None
        if not isinstance(ids, list) or len(ids) != len(records):
            raise InvalidAnswerError("the storage service sent no id for each record")
        return [str(item) for item in ids]

    def record(self, record_id: str) -> StoredRecord:
        """The record as this node answers it, unchecked: a node can send any record under
        the id. :meth:`verified_record` is the one the chain vouches for."""
        stored = _stored(self.get_json(f"/v1/records/{quote(record_id, safe='')}"))
        _check_answered("record", record_id, stored.id)
        return stored

    def verified_record(
        self,
        record_id: str,
        rpc: EthCall,
        *,
        anchor_log: str,
        chain_id: int | None = None,
        node: str | None = None,
        wait_s: float = 0.0,
    ) -> RecordProof:
        """``record_id``'s record (``.record``), proved by this node and checked against the
        chain, so a robot trusts only ``rpc`` and ``anchor_log``, never the node.

        ``rpc`` is a JSON-RPC request function the robot trusts (``JsonRpcClient.request``);
        the anchor must be on ``chain_id``, by default the chain ``rpc`` reads, and by
        ``node`` when given. A record not anchored yet is asked for again until ``wait_s``
        has passed: a node anchors an epoch seconds after its records arrive, so a robot
        that has just written or ingested one waits rather than retries. Raises
        ``RecordIdError`` for an id that is not one (nothing sent), ``ProofFormatError`` for
        a malformed proof, ``ProofVerificationError`` for one that does not hold,
        ``NotFoundError``/``ConflictError`` (409 ``not_anchored``) when the node has none
        (yet, after ``wait_s``).
        """
        wanted = str(RecordId.parse(record_id))
        body = self._anchored_proof(wanted, wait_s)
        return verify_record_proof(
            body,
            rpc,
            anchor_log=anchor_log,
            record_id=wanted,
            chain_id=rpc_chain_id(rpc) if chain_id is None else chain_id,
            node=node,
        )

    def _anchored_proof(self, record_id: str, wait_s: float) -> Any:
        """The node's proof of ``record_id``, asked for again while its epoch is not
        anchored, until ``wait_s`` has passed."""
        deadline = time.monotonic() + wait_s
        pause_s = ANCHOR_POLL_S
        while True:
            try:
                return self.get_json(f"/v1/records/{record_id}/proof")
            except ConflictError as exc:
                left_s = deadline - time.monotonic()
                if exc.code != "not_anchored" or left_s <= 0:
                    raise
            time.sleep(min(pause_s, left_s))
            pause_s = min(pause_s * 2, 1.0)

    def query(
        self,
        *,
        template: str | None = None,
        topic: str | None = None,
        robot: str | None = None,
        start: int | None = None,
        end: int | None = None,
        where: Sequence[str] = (),
        keywords: str | None = None,
        limit: int = 100,
        cursor: str | None = None,
    ) -> RecordPage:
        """One page of records matching every filter; ``next`` continues it. The records
        are the node's word, unchecked, as :meth:`record`'s."""
        params = record_filters(
            template=template,
            topic=topic,
            robot=robot,
            start=start,
            end=end,
            where=where,
            keywords=keywords,
        )
        params["limit"] = limit
        if cursor is not None:
            params["cursor"] = cursor
        answer = self.get_json("/v1/records", params=params)
        if not isinstance(answer, dict) or not isinstance(answer.get("records"), list):
            raise InvalidAnswerError("the storage service sent an invalid page of records")
        if len(answer["records"]) > limit:
            raise InvalidAnswerError(
                f"asked for {limit} records, the storage service sent {len(answer['records'])}"
            )
        following = answer.get("next")
        pending = answer.get("keywords_pending") or 0
        if isinstance(pending, bool) or not isinstance(pending, int) or pending < 0:
            raise InvalidAnswerError(
                f"the storage service sent keywords_pending {str(pending)[:80]!r}, not a count"
            )
        return RecordPage(
            [_stored(item) for item in answer["records"]],
            following if isinstance(following, str) else None,
            pending,
        )

    def intervals(
        self,
        template: str,
        field: str,
        value: str,
        *,
        robot: str | None = None,
        start: int | None = None,
        end: int | None = None,
    ) -> list[Interval]:
        params = {
            "template": template,
            "field": field,
            "value": value,
            "robot": robot,
            "start": start,
            "end": end,
        }
        answer = self.get_json(
            "/v1/intervals", params={k: v for k, v in params.items() if v is not None}
        )
        try:
            return [Interval.from_json(item) for item in answer["intervals"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidAnswerError(f"the storage service sent invalid intervals: {exc}") from exc


def record_filters(
    *,
    template: str | None = None,
    topic: str | None = None,
    robot: str | None = None,
    start: int | None = None,
    end: int | None = None,
    where: Sequence[str] = (),
    keywords: str | None = None,
) -> dict[str, Any]:
    """The query parameters selecting the records that pass every filter given, as
    ``GET /v1/records`` and ``GET /v1/export`` take them: ``where`` is repeated (httpx sends a
    list value as one key a clause)."""
    given = {
        "template": template,
        "topic": topic,
        "robot": robot,
        "start": start,
        "end": end,
        "keywords": keywords,
    }
    params: dict[str, Any] = {key: value for key, value in given.items() if value is not None}
    if where:
        params["where"] = list(where)
    return params


def _check_answered(kind: str, asked: str, answered: str) -> None:
    """Refuse an answer about another resource than the one asked for: the robot would
    validate its records against, or act on, a template or record it never named."""
    if answered != asked:
        raise InvalidAnswerError(
            f"asked for {kind} {asked[:100]!r}, the storage service sent {answered[:100]!r}"
        )


def _stored(item: Any) -> StoredRecord:
    if (
        not isinstance(item, dict)
        or not isinstance(item.get("id"), str)
        or not isinstance(item.get("record"), dict)
    ):
        raise InvalidAnswerError(
            f"the storage service sent an invalid record: {json.dumps(item)[:200]}"
        )
    meta = item.get("meta")
    return StoredRecord(
        item["id"],
        item["record"],
        _optional_text(item, "signer"),
        meta if isinstance(meta, dict) else None,
    )


def _is_time(value: Any) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool)


def _optional_text(answer: dict[str, Any], key: str) -> str | None:
    """``answer[key]``, text or absent: a number or an object there would reach the robot
    typed as text, to fail as a bare AttributeError at its first use."""
    value = answer.get(key)
    if value is not None and not isinstance(value, str):
        raise InvalidAnswerError(
            f"the storage service sent a {key} that is not text: {value!r:.100}"
        )
    return value
