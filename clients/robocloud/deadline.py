"""An HTTP transport whose reads end at the deadline of the answer being read.

httpx's ``timeout`` bounds each read, not an answer: a service that drips its status line and
headers one byte just inside it holds the client until h11's 100 KiB header cap, months at a
byte per 29 s, before the client sees a response it could time. So the deadline is enforced
where the bytes arrive: within :func:`reads_bounded_by`, every read of a connection is given
at most the time left on the current :class:`AnswerClock` (a context variable, so per
thread), and past it fails as httpx's ``ReadTimeout``. Outside such a block, as while a
caller reads a streamed body, reads keep httpx's own per-read timeout, and the body as a whole
has a lowest speed instead (:class:`LowSpeedGuard`): a body may be as large as its reader
allows, so no deadline fits it, but one dripped a byte per read would otherwise last as long
as its size.
"""

from __future__ import annotations

import functools
import os
import ssl
import time
import urllib.request
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import Any

import httpcore
import httpx


@dataclass
class AnswerClock:
    """When the answer to the request being exchanged must be complete: ``budget_s`` after
    the request's last byte left. A slow upload is the robot's own time, not the answer's,
    so every write the transport makes starts the clock again."""

    budget_s: float
    sent_at: float = field(default_factory=time.monotonic)

    def sent(self) -> None:
        self.sent_at = time.monotonic()

    @property
    def left_s(self) -> float:
        return self.sent_at + self.budget_s - time.monotonic()


@dataclass(frozen=True)
class LowSpeed:
    """The slowest a streamed body may come, as curl's ``--speed-limit``/``--speed-time``:
    fewer than ``min_bytes`` in any ``window_s`` ends it."""

    min_bytes: int = 1024
    window_s: float = 60.0


class LowSpeedGuard(httpx.SyncByteStream):
    """A response body that fails as httpx's ``ReadTimeout`` once a whole window has passed
    with fewer bytes than ``speed`` requires.

    The bytes are counted as they reach the reader, so a window is checked when a read
    returns: a service that sends nothing at all is ended by the per-read timeout first.
    """

    def __init__(
        self,
        body: httpx.SyncByteStream,
        speed: LowSpeed,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._body = body
        self._speed = speed
        self._clock = clock

    def __iter__(self) -> Iterator[bytes]:
        window_start, window_bytes = self._clock(), 0
        for chunk in self._body:
            window_bytes += len(chunk)
            now = self._clock()
            if now - window_start >= self._speed.window_s:
                if window_bytes < self._speed.min_bytes:
                    raise httpx.ReadTimeout(
                        f"the answer's body came too slowly: {window_bytes} bytes in "
                        f"{now - window_start:.0f} s, under {self._speed.min_bytes} in "
                        f"{self._speed.window_s:g} s"
                    )
                window_start, window_bytes = now, 0
            yield chunk

    def close(self) -> None:
        self._body.close()


_clock: ContextVar[AnswerClock | None] = ContextVar("robocloud_answer_clock", default=None)


@contextmanager
def reads_bounded_by(clock: AnswerClock) -> Iterator[None]:
    """Within the block, a :class:`DeadlineTransport`'s writes restart ``clock`` and its reads
    end when ``clock`` runs out."""
    token = _clock.set(clock)
    try:
        yield
    finally:
        _clock.reset(token)


def _read_timeout(timeout: float | None) -> float | None:
    """``timeout`` shortened to the time left on the current clock, if there is one."""
    clock = _clock.get()
    if clock is None:
        return timeout
    left = clock.left_s
    if left <= 0:
        raise httpcore.ReadTimeout("the answer's deadline has passed")
    return left if timeout is None else min(timeout, left)


class _DeadlineStream(httpcore.NetworkStream):
    """A connection whose reads respect the current :class:`AnswerClock`, and whose writes
    restart it."""

    def __init__(self, stream: httpcore.NetworkStream) -> None:
        self._stream = stream

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return self._stream.read(max_bytes, _read_timeout(timeout))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        self._stream.write(buffer, timeout)
        clock = _clock.get()
        if clock is not None:
            clock.sent()

    def close(self) -> None:
        self._stream.close()

    def start_tls(
        self,
        ssl_context: ssl.SSLContext,
        server_hostname: str | None = None,
        timeout: float | None = None,
    ) -> httpcore.NetworkStream:
        return _DeadlineStream(self._stream.start_tls(ssl_context, server_hostname, timeout))

    def get_extra_info(self, info: str) -> Any:
        return self._stream.get_extra_info(info)


class _DeadlineBackend(httpcore.NetworkBackend):
    """httpcore's socket backend, its connections wrapped in :class:`_DeadlineStream`."""

    def __init__(self) -> None:
        self._backend = httpcore.SyncBackend()

    def connect_tcp(
        self,
        host: str,
        port: int,
        timeout: float | None = None,
        local_address: str | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore.NetworkStream:
        stream = self._backend.connect_tcp(host, port, timeout, local_address, socket_options)
        return _DeadlineStream(stream)

    def connect_unix_socket(
        self,
        path: str,
        timeout: float | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore.NetworkStream:
        return _DeadlineStream(self._backend.connect_unix_socket(path, timeout, socket_options))

    def sleep(self, seconds: float) -> None:
        self._backend.sleep(seconds)


class DeadlineTransport(httpx.HTTPTransport):
    """httpx's default transport, over connections that honour :func:`reads_bounded_by`;
    through the HTTP(S) proxy at ``proxy``, if there is one.

    httpx builds its connection pool with no way to name a network backend, so the pool is
    built here with httpx's defaults and this module's backend (httpcore's public
    ``network_backend`` argument). ``HTTPTransport.__init__`` is not called: all it does is
    build a pool of its own, and with it a TLS context (20 ms of loading CA certificates), only
    for this one to replace it; its methods use nothing but ``_pool``.

    The TLS context is the process's one (:func:`tls_context`), and only a transport that
    may speak TLS to its service (``tls``: the service's URL is ``https``) asks for it. A
    transport made without it that is sent to an ``https`` URL all the same still verifies:
    httpcore then makes its own default context, certifi's authorities.
    """

    def __init__(self, proxy: str | None = None, *, tls: bool = True) -> None:
        limits = httpx.Limits(max_connections=100, max_keepalive_connections=20)
        pool_options: dict[str, Any] = {
            "ssl_context": tls_context() if tls else None,
            "max_connections": limits.max_connections,
            "max_keepalive_connections": limits.max_keepalive_connections,
            "keepalive_expiry": limits.keepalive_expiry,
            "network_backend": _DeadlineBackend(),
        }
        if proxy is None:
            self._pool = httpcore.ConnectionPool(**pool_options)
            return
        via = httpx.Proxy(proxy)
        self._pool = httpcore.HTTPProxy(
            proxy_url=httpcore.URL(
                scheme=via.url.raw_scheme,
                host=via.url.raw_host,
                port=via.url.port,
                target=via.url.raw_path,
            ),
            proxy_auth=via.raw_auth,
            proxy_headers=via.headers.raw,
            proxy_ssl_context=via.ssl_context,
            **pool_options,
        )


def tls_context() -> ssl.SSLContext:
    """The TLS context every SDK client shares: httpx's default (certificates verified against
    ``SSL_CERT_FILE`` or ``SSL_CERT_DIR`` when set, else certifi's), made once for each value
    of those variables instead of once a client. Loading the authorities took 20 ms, twice a
    client, which every command and every service's connection to another paid."""
    return _tls_context_for(os.environ.get("SSL_CERT_FILE"), os.environ.get("SSL_CERT_DIR"))


@functools.cache
def _tls_context_for(cert_file: str | None, cert_dir: str | None) -> ssl.SSLContext:
    """httpx reads the two variables itself; they are this cache's key so that a context
    never outlives the authorities it was made from."""
    return httpx.create_ssl_context()


def transport_for(base_url: str) -> httpx.BaseTransport:
    """The transport of an SDK client of ``base_url``.

    A client given a transport no longer reads proxies from the environment, so this picks
    the one httpx would have picked (``<scheme>_proxy`` or ``all_proxy``, unless ``no_proxy``
    names the host). A SOCKS proxy gets httpx's own transport, whose answers the client
    still times between reads.
    """
    url = httpx.URL(base_url)
    tls = url.scheme == "https"
    proxies = urllib.request.getproxies()
    proxy = proxies.get(url.scheme) or proxies.get("all")
    if not proxy or urllib.request.proxy_bypass(url.host):
        return DeadlineTransport(tls=tls)
    if "://" not in proxy:
        proxy = f"http://{proxy}"
    if not proxy.startswith(("http://", "https://")):
        return httpx.HTTPTransport(proxy=proxy, verify=tls_context())
    return DeadlineTransport(proxy, tls=tls)
