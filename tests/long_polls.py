"""A crowd of long polls at once: the tests of a service's bound on the reads that wait."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

import anyio
import httpx


async def crowd_of_waits(
    url: str,
    path: str,
    params: dict[str, Any],
    waiting: int,
    extra: int,
    meanwhile: Callable[[httpx.AsyncClient], Awaitable[None]] | None = None,
) -> tuple[list[Any], list[Any]]:
    """``waiting + extra`` reads of ``path`` at once, each asking to wait: the answers of the
    ``extra`` answered at once (past the service's bound), and then, once ``meanwhile`` has
    done what ends the wait (with the same client, while the others still wait), the others'
    answers. Every answer must be a 200."""

    async def read(client: httpx.AsyncClient) -> Any:
        answer = await client.get(path, params=params)
        assert answer.status_code == 200, answer.text
        return answer.json()

    limits = httpx.Limits(max_connections=waiting + extra)
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=60) as client:
        reads = [asyncio.create_task(read(client)) for _ in range(waiting + extra)]
        with anyio.fail_after(20):
            while sum(task.done() for task in reads) < extra:
                await asyncio.sleep(0.05)
        await asyncio.sleep(0.5)
        early = [task for task in reads if task.done()]
        if meanwhile is not None:
            await meanwhile(client)
        with anyio.fail_after(120):
            await asyncio.gather(*reads)
    return [task.result() for task in early], [task.result() for task in reads if task not in early]
