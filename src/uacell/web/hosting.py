"""Run the web HMI: its client certificate, HTTPS, and uvicorn in the caller's event loop.

``start_web(...)`` binds the port, starts serving and returns a ``RunningWeb`` whose ``url`` is what
the listening line prints; ``await running.stop()`` ends it (and every web user's OPC UA session).

Files, in the data directory's ``web/``:

- ``pki/own/cert.der`` and ``key.pem``: the HMI's application instance certificate
  (``urn:uacell:web``); the OPC UA server must trust it (``uacell serve`` does so itself when it runs
  the HMI beside it; a remote server: move it from that server's ``pki/rejected/`` to ``pki/trusted/``);
- ``pki/server/<host>_<port>.der``: the server certificate the HMI accepted on first connection
  (trust on first use); a server that later presents another certificate is not talked to;
- ``https/cert.pem``: the server certificate in PEM, for HTTPS when none is configured.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import re
import socket
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlparse

import uvicorn
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from uacell.core.companion import Companion, web_views
from uacell.core.errors import ConfigError
from uacell.core.files import atomic_write
from uacell.core.roles import is_loopback
from uacell.security.chain import first_certificate
from uacell.security.pki import (
    PkiPaths,
    TrustList,
    cert_to_der,
    coverage_problems,
    generate_key,
    key_to_pem,
    make_certificate,
    thumbprint,
)
from uacell.web.app import RELEASE_AFTER, UA_SESSIONS, WebApp, cookie_name
from uacell.web.guards import HEADER_TIMEOUT, machine_names, timed_headers
from uacell.web.uasession import APPLICATION_URI, Credentials

if TYPE_CHECKING:  # the annotation only: the HMI is a client and does not load the server's parts
    from uacell.host import ServerView

log = logging.getLogger(__name__)


def web_dir(data_dir: Path) -> Path:
    return Path(data_dir) / "web"


def hmi_certificate(data_dir: Path) -> tuple[Path, Path]:
    """Make (or reuse) the HMI's own client certificate; returns (cert.der, key.pem)."""
    paths = PkiPaths(web_dir(data_dir) / "pki")
    if paths.cert.exists() and paths.key.exists():
        try:
            cert = x509.load_der_x509_certificate(paths.cert.read_bytes())
            if not coverage_problems(cert, APPLICATION_URI, []):
                return paths.cert, paths.key
        except ValueError:
            pass
    paths.create()
    key = generate_key()
    cert = make_certificate(
        key,
        APPLICATION_URI,
        common_name=f"uacell web HMI@{socket.gethostname()}",
        dns_names=[socket.gethostname()],
        server=False,
        client=True,
    )
    atomic_write(paths.key, key_to_pem(key), mode=0o600)
    der = cert_to_der(cert)
    atomic_write(paths.cert, der, mode=0o644)
    log.info("created the web HMI's certificate %s (thumbprint %s)", paths.cert, thumbprint(der))
    return paths.cert, paths.key


def trust_hmi(data_dir: Path) -> None:
    """Put the HMI's certificate into the trust list of the server whose data directory this is."""
    cert, _ = hmi_certificate(data_dir)
    trust = TrustList(PkiPaths.in_data_dir(data_dir))
    der = cert.read_bytes()
    if not trust.is_trusted(der):
        log.info("trusting the web HMI's certificate %s", trust.trust(der))


async def pinned_server_certificate(data_dir: Path, url: str) -> Path:
    """The server certificate the HMI trusts for ``url``: pinned on first connection, then required."""
    parsed = urlparse(url)
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", f"{parsed.hostname}_{parsed.port or 4840}")
    pinned = web_dir(data_dir) / "pki" / "server" / f"{name}.der"
    if pinned.exists():
        return pinned
    client = Client(url, timeout=10)
    endpoints = await client.connect_and_get_server_endpoints()
    endpoint = Client.find_endpoint(endpoints, ua.MessageSecurityMode.SignAndEncrypt, SecurityPolicyBasic256Sha256.URI)
    der = first_certificate(endpoint.ServerCertificate)  # its CA's may follow (OPC 10000-6 6.2.6)
    x509.load_der_x509_certificate(der)
    pinned.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(pinned, der, mode=0o644)
    log.warning(
        "web: trusting the certificate of %s on first use (thumbprint %s), kept in %s", url, thumbprint(der), pinned
    )
    return pinned


def _pem_copy(der_path: Path, target: Path) -> Path:
    cert = x509.load_der_x509_certificate(der_path.read_bytes())
    target.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(target, cert.public_bytes(serialization.Encoding.PEM), mode=0o644)
    return target


@dataclass
class RunningWeb:
    url: str
    web: WebApp
    server: uvicorn.Server
    sock: socket.socket
    task: asyncio.Task[None]

    async def stop(self) -> None:
        await self.web.close()
        self.server.should_exit = True
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self.task, 10)
        with contextlib.suppress(Exception):
            await self.server.shutdown(sockets=[self.sock])
        self.sock.close()


def _bind(host: str, port: int) -> socket.socket:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        reason = "address already in use" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
        raise ConfigError(
            f"web: cannot listen on {host}:{port}: {reason} (choose another with --web-port/--port "
            "or [web] port, or turn the HMI off with --no-web or [web] enabled = false)"
        ) from None
    sock.listen(128)
    sock.setblocking(False)
    return sock


async def start_web(
    server_url: str,
    data_dir: Path,
    *,
    companions: Sequence[Companion[ServerView]],
    host: str = "127.0.0.1",
    port: int = 8080,
    server_certificate: Path | Callable[[], bytes] | None = None,
    https_certificate: Path | None = None,
    https_key: Path | None = None,
    ua_sessions: int = UA_SESSIONS,
    release_after: float = RELEASE_AFTER,
    header_timeout: float = HEADER_TIMEOUT,
) -> RunningWeb:
    """Serve the HMI for the OPC UA server ``server_url``; HTTPS on every non-loopback address.

    ``server_certificate`` is the OPC UA server's certificate when known: a DER file, or beside the
    server a function giving what the server sends now; otherwise it is pinned on first connection.
    HTTPS needs ``https_certificate`` and ``https_key`` (PEM, or a DER certificate) unless ``host`` is
    loopback. ``ua_sessions``, ``release_after`` and
    ``header_timeout`` are the ``[web]`` settings of the same names (docs/configuration.md).
    The page shows the parts of ``companions`` (the composition root's, the server's) that declare a
    web view.
    """
    cert, key = hmi_certificate(data_dir)
    https = not is_loopback(host)
    ssl_cert = ssl_key = None
    if https:
        if https_certificate is None or https_key is None:
            raise ConfigError(
                f"web: {host} is not a loopback address, so the HMI is served over HTTPS only; "
                "set [web] certificate and private_key (PEM files)"
            )
        ssl_cert = str(https_certificate)
        if https_certificate.suffix.lower() in (".der", ".cer"):
            ssl_cert = str(_pem_copy(https_certificate, web_dir(data_dir) / "https" / "cert.pem"))
        ssl_key = str(https_key)
    if server_certificate is None:
        try:
            server_certificate = await pinned_server_certificate(data_dir, server_url)
        except Exception as exc:  # not reachable yet: the page says so and keeps trying
            log.warning("web: cannot reach %s yet (%s); the HMI keeps trying", server_url, type(exc).__name__)
    credentials = Credentials(cert, key, server_certificate)
    # Anonymous visitors get the server's anonymous role, which on a loopback-only server is meant for
    # the local machine: an HMI on the network then takes logged-in users only.
    anonymous = not https or not is_loopback(urlparse(server_url).hostname or "")
    web = WebApp(
        server_url,
        credentials,
        https=https,
        anonymous=anonymous,
        hosts=(host, *machine_names()),
        ua_sessions=ua_sessions,
        release_after=release_after,
        views=web_views(companions),
    )
    sock = _bind(host, port)
    config = uvicorn.Config(
        web.app,
        log_level="warning",
        access_log=False,
        lifespan="off",
        ssl_certfile=ssl_cert,
        ssl_keyfile=ssl_key,
        timeout_graceful_shutdown=3,
        http=timed_headers(header_timeout),
    )
    config.load()
    server = uvicorn.Server(config)
    server.lifespan = config.lifespan_class(config)
    await server.startup(sockets=[sock])
    task = asyncio.get_running_loop().create_task(server.main_loop())
    bound_host, bound_port = sock.getsockname()[:2]
    web.cookie = cookie_name(bound_port, https)
    shown = f"[{bound_host}]" if ":" in bound_host else bound_host
    url = f"{'https' if https else 'http'}://{shown}:{bound_port}/"
    return RunningWeb(url, web, server, sock, task)
