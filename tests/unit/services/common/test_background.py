"""Background tasks: one that fails is named by /readyz and takes nothing else down."""

from __future__ import annotations

from pathlib import Path

import anyio
import httpx
import pytest

from services.cas.app import build_app
from services.cas.settings import CasSettings
from services.common.background import BackgroundTasks


def test_a_failed_task_is_recorded_and_its_group_goes_on() -> None:
    background = BackgroundTasks()
    rounds: list[int] = []

    async def failing() -> None:
        raise OSError(28, "No space left on device")

    async def counting() -> None:
        while True:
            rounds.append(len(rounds))
            await anyio.sleep(0)

    async def main() -> None:
        async with anyio.create_task_group() as group:
            background.start(group, "collection", failing)
            background.start(group, "index", counting)
            while len(rounds) < 20:
                await anyio.sleep(0)
            group.cancel_scope.cancel()
        with pytest.raises(RuntimeError, match="background task collection failed: OSError"):
            await background.all_running()

    anyio.run(main)
    assert background.failed == {"collection": "OSError: [Errno 28] No space left on device"}


def test_a_failed_garbage_collection_round_leaves_the_cas_serving_and_collecting(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One failed collection cancelled the lifespan's task group: the lifespan's shutdown
    closed the nonce journal under a server still serving (a signed write's nonce line went
    into a client's socket) and collection never ran again, while /readyz answered 200."""
    app = build_app(CasSettings(data_dir=tmp_path, cas_gc_interval_s=0.01, auth="signed"))
    store = app.state.store
    rounds: list[str] = []
    collect = store.collect_garbage

    def failing_once(grace_s: float) -> list[object]:
        rounds.append("failed" if not rounds else "collected")
        if len(rounds) == 1:
            raise FileNotFoundError("packs/0179.pack")
        return list(collect(grace_s))

    monkeypatch.setattr(store, "collect_garbage", failing_once)

    async def main() -> httpx.Response:
        async with app.router.lifespan_context(app):
            with anyio.fail_after(30):
                while len(rounds) < 3:
                    await anyio.sleep(0.01)
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(transport=transport, base_url="http://cas") as client:
                return await client.get("/readyz")

    ready = anyio.run(main)
    assert rounds[:3] == ["failed", "collected", "collected"]
    assert ready.json()["status"] == "ready"
