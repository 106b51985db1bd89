"""Helper processes that end with the service that started them.

The service hands work to processes of its own: SPARQL workers and the executors they fork
(:mod:`services.storage.sparql`), and the processes that stage a bag
(:mod:`services.storage.staging`). Each learns of the service's death when it next reads or
writes the pipe between them, but one stuck in computation (a query evaluating for ever, a
bag's message decoding) does neither: after a ``kill -9`` of the service such processes ran
on, at gigabytes of memory, with no one left to stop them. The kernel can stop them instead.
"""

from __future__ import annotations

import contextlib
import ctypes
import signal

PR_SET_PDEATHSIG = 1
"""Linux's prctl(2) option: the signal this process gets when its parent ends."""


def die_with_parent() -> None:
    """Have the kernel kill this process (SIGKILL) as soon as its parent ends, whatever it is
    doing then. The parent is the process that forked this one (for a staging process, the
    forkserver, which ends when the service does), and a process whose parent ended before
    this call is not signalled: callers say why that leaves none running. A no-op where
    there is no prctl (another system)."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
