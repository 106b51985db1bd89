"""Tasks that run beside a service for its lifetime: periodic collection, index following.

A task is started in the lifespan's task group, and an exception escaping a task cancels that
group: the lifespan then ran its shutdown (the nonce journal closed, the store closed) while
the server went on accepting requests. The cas did exactly that after one failed garbage
collection: a signed write's nonce line went to whichever client socket had taken the closed
journal's file descriptor, and ``/readyz`` still answered 200. So a task that fails here is
logged with its traceback and named by ``/readyz`` (503) until the service restarts; the
lifespan and every other task go on.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable

from anyio.abc import TaskGroup

from robocloud.errors import shown_text

log = logging.getLogger("robocloud.background")


class BackgroundTasks:
    """The service's background tasks and which of them failed."""

    def __init__(self) -> None:
        self.failed: dict[str, str] = {}

    def start(self, group: TaskGroup, name: str, task: Callable[[], Awaitable[None]]) -> None:
        """Run ``task`` in ``group``; its failure is recorded, never raised into ``group``."""
        group.start_soon(self._run, name, task, name=name)

    async def _run(self, name: str, task: Callable[[], Awaitable[None]]) -> None:
        try:
            await task()
        except Exception as exc:
            log.exception("background task failed", extra={"task": name})
            self.failed[name] = shown_text(f"{type(exc).__name__}: {exc}")

    async def all_running(self) -> None:
        """A readiness check: fails while any task has failed."""
        if self.failed:
            raise RuntimeError(
                "; ".join(
                    f"background task {name} failed: {why}" for name, why in self.failed.items()
                )
            )
