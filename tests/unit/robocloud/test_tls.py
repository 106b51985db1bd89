"""A robot reaches a service over https: the certificate is verified against the authorities
the environment names (``SSL_CERT_FILE``), and the authorities are loaded once a process, not
once a client (20 ms each time, twice a client, paid by every command and every service's
connection to another)."""

from __future__ import annotations

import datetime
import ipaddress
import ssl
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler
from pathlib import Path
from typing import Any

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from robocloud.client import ServiceClient
from robocloud.errors import ConnectError
from tests.scripted_http import serving

ANSWER = b'{"over": "tls"}'


def self_signed(directory: Path) -> tuple[Path, Path]:
    """A certificate for 127.0.0.1 that no public authority signed, and its key."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "robocloud test service")])
    now = datetime.datetime.now(datetime.UTC)
    certificate = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(hours=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    cert_path, key_path = directory / "service.pem", directory / "service.key"
    cert_path.write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return cert_path, key_path


@contextmanager
def tls_service(cert_path: Path, key_path: Path) -> Iterator[str]:
    """A service answering ``ANSWER`` over TLS on a free loopback port; its base URL."""

    class Answer(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(ANSWER)))
            self.end_headers()
            self.wfile.write(ANSWER)

        def log_message(self, *args: object) -> None:
            return None

    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(cert_path, key_path)
    with serving(Answer, tls=context) as url:
        yield url


@pytest.fixture
def certificate(tmp_path: Path) -> tuple[Path, Path]:
    return self_signed(tmp_path)


@pytest.fixture
def contexts_made(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """Every TLS client context made from here on (httpx makes its own with this call)."""
    made: list[Any] = []
    create = ssl.create_default_context

    def counting(*args: Any, **kwargs: Any) -> ssl.SSLContext:
        made.append(kwargs.get("cafile") or kwargs.get("capath"))
        return create(*args, **kwargs)

    monkeypatch.setattr(ssl, "create_default_context", counting)
    return made


def test_a_certificate_no_trusted_authority_signed_is_refused(
    certificate: tuple[Path, Path],
) -> None:
    with (
        tls_service(*certificate) as url,
        ServiceClient(url, timeout=5, retries=0) as client,
        pytest.raises(ConnectError, match="CERTIFICATE_VERIFY_FAILED"),
    ):
        client.get_json("/v1/thing")


def test_the_authorities_the_environment_names_are_the_ones_trusted(
    certificate: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``SSL_CERT_FILE`` is read as httpx reads it, even after a client made without it."""
    with tls_service(*certificate) as url:
        ServiceClient(url, timeout=5, retries=0).close()
        monkeypatch.setenv("SSL_CERT_FILE", str(certificate[0]))
        with ServiceClient(url, timeout=5, retries=0) as client:
            assert client.get_json("/v1/thing") == {"over": "tls"}


def test_clients_of_https_services_load_the_authorities_once(
    certificate: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch, contexts_made: list[Any]
) -> None:
    monkeypatch.setenv("SSL_CERT_FILE", str(certificate[0]))
    with tls_service(*certificate) as url:
        for _ in range(20):
            with ServiceClient(url, timeout=5, retries=0) as client:
                assert client.get_json("/v1/thing") == {"over": "tls"}
    assert contexts_made == [str(certificate[0])]


def test_clients_of_http_services_load_no_authorities(contexts_made: list[Any]) -> None:
    for _ in range(20):
        ServiceClient("http://127.0.0.1:9", timeout=5, retries=0).close()
    assert contexts_made == []
