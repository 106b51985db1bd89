"""Domain exceptions become JSON errors through the service's ErrorMap, in process."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import httpx
from fastapi import APIRouter

from robocloud.bounded_json import JsonDepthError, loads
from robocloud.cid import CIDError, parse_cid
from services.common.app import create_app
from services.common.errors import COMMON_ERRORS, ErrorMap, ErrorRule, NotFound
from services.common.settings import ServiceSettings


class ThingMissing(Exception):
    def __init__(self, name: str) -> None:
        super().__init__(f"no thing named {name}")
        self.name = name


class ThingGone(ThingMissing):
    """A subclass is answered by its parent's rule unless it has its own."""


class Unmapped(Exception):
    pass


ERRORS = ErrorMap({ThingMissing: ErrorRule(404, "thing_not_found", lambda exc: {"name": exc.name})})


def _get(tmp_path: Path, path: str) -> httpx.Response:
    router = APIRouter()

    @router.get("/missing")
    async def missing() -> None:
        raise ThingMissing("a")

    @router.get("/echo")
    async def echo() -> None:
        raise ThingMissing("half a pair \udc80")

    @router.get("/gone")
    async def gone() -> None:
        raise ThingGone("b")

    @router.get("/http")
    async def http() -> None:
        raise NotFound("plain", code="plain_not_found", details={"x": 1})

    @router.get("/unmapped")
    async def unmapped() -> None:
        raise Unmapped("secret detail")

    settings = ServiceSettings(service="test", data_dir=tmp_path, auth="signed")
    app = create_app("test", settings, routers=[router], errors=ERRORS)

    async def call() -> httpx.Response:
        transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            return await client.get(path)

    return asyncio.run(call())


def _error(response: httpx.Response) -> dict[str, Any]:
    error: dict[str, Any] = response.json()["error"]
    assert error["request_id"] == response.headers["x-request-id"]
    return error


def test_a_mapped_domain_exception_gets_its_status_code_and_details(tmp_path: Path) -> None:
    response = _get(tmp_path, "/missing")
    assert response.status_code == 404
    error = _error(response)
    assert (error["code"], error["message"], error["details"]) == (
        "thing_not_found",
        "no thing named a",
        {"name": "a"},
    )


def test_an_error_echoing_a_lone_surrogate_is_still_answered(tmp_path: Path) -> None:
    """Such a string cannot be encoded as UTF-8: the error answer itself was a 500."""
    response = _get(tmp_path, "/echo")
    assert response.status_code == 404
    error = _error(response)
    assert (error["message"], error["details"]) == (
        "no thing named half a pair \ufffd",
        {"name": "half a pair \ufffd"},
    )
    loads(response.content)


def test_a_subclass_uses_its_parents_rule(tmp_path: Path) -> None:
    response = _get(tmp_path, "/gone")
    assert response.status_code == 404
    assert _error(response)["details"] == {"name": "b"}


def test_service_errors_keep_their_own_status(tmp_path: Path) -> None:
    response = _get(tmp_path, "/http")
    assert response.status_code == 404
    assert _error(response)["code"] == "plain_not_found"


def test_an_unmapped_exception_is_a_500_without_its_message(tmp_path: Path) -> None:
    response = _get(tmp_path, "/unmapped")
    assert response.status_code == 500
    error = _error(response)
    assert error["code"] == "internal_error"
    assert "secret" not in error["message"]


def test_format_errors_of_the_sdk_are_answered_alike_everywhere() -> None:

    try:
        parse_cid("bafy-not-a-cid", "arg")
    except CIDError as exc:
        error = COMMON_ERRORS.to_service_error(exc)
    assert error is not None
    assert (error.status, error.code, error.details) == (
        400,
        "invalid_cid",
        {"field": "arg", "cid": "bafy-not-a-cid"},
    )
    try:
        loads(b"[" * 100)
    except JsonDepthError as exc:
        error = COMMON_ERRORS.to_service_error(exc)
    assert error is not None
    assert (error.status, error.code, error.details) == (400, "json_too_deep", {"max_depth": 64})
