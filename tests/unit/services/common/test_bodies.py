"""JSON bodies: a large one is parsed off the event loop, so the service's other requests
are answered while it is; a small one is parsed where it is, a thread hop costing more."""

from __future__ import annotations

import asyncio
import threading

import httpx
import pytest
from fastapi import Depends, FastAPI
from pydantic import BaseModel

from robocloud import bounded_json
from services.common import bodies


class Numbers(BaseModel):
    values: list[int]


def parsed_on(monkeypatch: pytest.MonkeyPatch, body: bytes) -> tuple[int, bool]:
    """The status of a POST of ``body`` and whether it was parsed on the loop's thread."""
    app = FastAPI()
    threads: list[threading.Thread] = []
    loads = bounded_json.loads

    def recorded(raw: bytes, **options: int) -> object:
        threads.append(threading.current_thread())
        return loads(raw, **options)

    monkeypatch.setattr(bodies.bounded_json, "loads", recorded)

    @app.post("/numbers")
    async def numbers(body: Numbers = Depends(bodies.json_body(Numbers))) -> int:
        return len(body.values)

    async def post() -> tuple[int, threading.Thread]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            response = await client.post(
                "/numbers", content=body, headers={"Content-Type": "application/json"}
            )
        return response.status_code, threading.current_thread()

    status, loop_thread = asyncio.run(post())
    return status, threads == [loop_thread]


def test_a_small_body_is_parsed_on_the_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    assert parsed_on(monkeypatch, b'{"values": [1, 2, 3]}') == (200, True)


def test_a_large_body_is_parsed_on_a_worker_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    """16 MiB of nested arrays took 8 s of the loop; ``/healthz`` waited as long."""
    values = ", ".join(["7"] * (bodies.INLINE_JSON_BYTES // 3 + 1))
    assert parsed_on(monkeypatch, f'{{"values": [{values}]}}'.encode()) == (200, False)
