"""Processes that end with the one that started them, and hold no more memory than given.

A service hands work to processes of its own: storage's SPARQL workers and the executors they
fork (:mod:`services.storage.sparql`), the processes that stage a bag
(:mod:`services.storage.staging`), and ``make up``'s supervisor its services. Each learns of
its parent's death when it next reads or writes the pipe between them, but one stuck in
computation (a query evaluating for ever, a bag's message decoding) does neither: after a
``kill -9`` of the service such processes ran on, at gigabytes of memory, with no one left to
stop them. The kernel can stop them instead, and can bound what each maps, so that input
that decodes to more than it holds ends as an error in the worker instead of the machine
swapping.
"""

from __future__ import annotations

import contextlib
import ctypes
import resource
import signal

PR_SET_PDEATHSIG = 1
"""Linux's prctl(2) option: the signal this process gets when its parent ends."""


def die_with_parent(sent: signal.Signals = signal.SIGKILL) -> None:
    """Have the kernel send this process ``sent`` (SIGKILL unless told: a supervised service
    gets SIGTERM, to close its stores) as soon as its parent ends, whatever it is doing then.
    The parent is the *thread* that forked this process (for a staging process, the
    forkserver's one thread, which ends when the service does), so a thread that lives as
    long as the service must fork it; a process whose parent ended before this call is not
    signalled: callers say why that leaves none running. A no-op where there is no prctl
    (another system)."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, sent)


def limit_memory(limit: int) -> None:
    """Bound this process's address space to ``limit`` bytes (0: no bound): past it an
    allocation fails, which Python raises as :class:`MemoryError` where it happened. Address
    space, not resident memory, is what the kernel can refuse at the allocation itself; it
    counts the interpreter and its libraries (about 185 MB for a staging process) too."""
    if limit > 0:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
