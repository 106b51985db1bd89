"""``Knowledge``: describe what a robot holds and find what others hold, through a storage node.

A description is validated and stored here first (``store``), so a robot learns of a
violation before anything leaves it and the CID it advertises is the CID of the canonical
bytes it computed itself; the knowledge base then fetches those bytes from cas by CID and
checks them again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from robocloud import bounded_json
from robocloud.cas import Cas, CasError
from robocloud.cid import CID
from robocloud.client import ServiceClient
from robocloud.errors import FormatError, InvalidAnswerError
from robocloud.semantic import Description, validate

SPARQL_JSON = "application/sparql-results+json"


@dataclass(frozen=True)
class SparqlAnswer:
    """A SPARQL answer: its media type (without parameters) and its bytes."""

    media_type: str
    body: bytes


class Knowledge(ServiceClient):
    """The storage service's knowledge base: ``/v1/knowledge``."""

    default_service = "storage"

    def add(self, cid: CID | str) -> dict[str, Any]:
        """``POST /v1/knowledge`` (signed): index the description stored in cas at ``cid``."""
        answer = self.post_json("/v1/knowledge", {"cid": str(cid)})
        if not isinstance(answer, dict) or answer.get("cid") != str(cid):
            raise InvalidAnswerError(f"the knowledge base answered {str(answer)[:200]} for {cid}")
        return answer

    def sparql(self, query: str, *, accept: str = SPARQL_JSON) -> SparqlAnswer:
        """A SPARQL 1.1 Protocol query (POST form), answered in a format ``accept`` allows."""
        response = self.request(
            "POST",
            "/v1/knowledge/sparql",
            content=_form({"query": query}),
            headers={"Content-Type": "application/x-www-form-urlencoded", "Accept": accept},
            signed=False,
            idempotent=True,
        )
        media = response.headers.get("content-type", "").split(";")[0].strip().lower()
        return SparqlAnswer(media, response.content)

    def select(self, query: str) -> list[dict[str, str]]:
        """The rows of a SELECT query, each variable's value as text (unbound ones left out)."""
        body = self.sparql(query).body
        try:
            bindings = bounded_json.loads(body)["results"]["bindings"]
            return [_row(row) for row in bindings]
        except (FormatError, KeyError, TypeError, AttributeError) as exc:
            raise InvalidAnswerError(f"not SPARQL JSON results: {exc}") from None

    def applications(
        self, consumes: str, *, produces: str | None = None, limit: int = 100
    ) -> list[dict[str, Any]]:
        """``GET /v1/knowledge/applications``: applications taking ``consumes`` (a media type
        such as ``image/jpeg``, or a template's ``ipfs://<cid>``)."""
        params: dict[str, Any] = {"consumes": consumes, "limit": limit}
        if produces is not None:
            params["produces"] = produces
        answer = self.get_json("/v1/knowledge/applications", params=params)
        found = answer.get("applications") if isinstance(answer, dict) else None
        if not isinstance(found, list) or not all(isinstance(item, dict) for item in found):
            raise InvalidAnswerError("the knowledge base's applications are not a list of objects")
        if len(found) > limit:
            raise InvalidAnswerError(
                f"asked for {limit} applications, the knowledge base sent {len(found)}"
            )
        return found

    def store(self, description: Description, cas: Cas) -> CID:
        """Validate ``description``, put its canonical bytes in ``cas`` and index them here.

        Raises ``DescriptionInvalidError`` before anything is sent when it fails its shapes.
        """
        validate(description)
        expected = description.cid()
        stored = cas.add_bytes(description.canonical())
        if stored != expected:
            raise CasError(f"cas stored the description as {stored}, its CID is {expected}")
        self.add(expected)
        return expected


def _row(row: dict[str, Any]) -> dict[str, str]:
    """One row's values, each a string as SPARQL 1.1 JSON results bind it: a number or an
    object there, ``str()``'d, reached the robot as text no triple held (``"5"``,
    ``"{'a': 1}"``, ``"None"``)."""
    values: dict[str, str] = {}
    for name, binding in row.items():
        value = binding["value"]
        if not isinstance(value, str):
            raise InvalidAnswerError(
                f"the knowledge base bound variable {name[:100]!r} to {value!r:.100}, not a string"
            )
        values[name] = value
    return values


def _form(fields: dict[str, str]) -> bytes:
    from urllib.parse import urlencode

    return urlencode(fields).encode()
