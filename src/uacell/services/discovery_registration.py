"""Registration with a Local Discovery Server (OPC 10000-4 5.5.6 RegisterServer2, OPC 10000-12).

With ``[discovery] url`` set, the server registers itself (IsOnline true, with an
MdnsDiscoveryConfiguration naming it and its capabilities) once it listens and again every
``interval`` seconds, and unregisters (IsOnline false) at a clean stop.

A discovery server must authenticate the registering server (OPC 10000-4 5.5.5): uacell opens the
SecureChannel with its own application certificate and private key (``pki/own``), SignAndEncrypt
where the discovery server offers it, Sign otherwise, with the strongest policy both know; the
ServerUri it registers is its ApplicationUri, the URI its certificate carries. asyncua's
``Server.register_to_discovery`` opens the channel without security and cannot be used for that.

A failed attempt (discovery server down, our certificate not yet trusted there, ...) is logged in one
line and tried again at the next interval; it never stops the server.
"""

from __future__ import annotations

import asyncio
import logging
import socket
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto import security_policies as sp

from uacell.core.background import Background
from uacell.security.chain import first_certificate

log = logging.getLogger(__name__)

__all__ = ["DiscoveryConfig", "DiscoveryRegistration", "Registrant", "discovery_url"]

# Strongest first; the first the discovery server offers in the best mode it offers is used.
POLICIES: tuple[type[sp.SecurityPolicy], ...] = (
    sp.SecurityPolicyAes256Sha256RsaPss,
    sp.SecurityPolicyBasic256Sha256,
    sp.SecurityPolicyAes128Sha256RsaOaep,
)
MODES = (ua.MessageSecurityMode.SignAndEncrypt, ua.MessageSecurityMode.Sign)
MDNS_NAME_BYTES = 63  # OPC 10000-4 7.9: less than 64 bytes


@dataclass(frozen=True)
class Registrant:
    """What the server registers as, and the credentials it proves it with."""

    server_uri: str
    product_uri: str
    name: str
    discovery_urls: Sequence[str]
    capabilities: Sequence[str]
    certificate: Path
    private_key: Path

    def parameters(self, online: bool) -> ua.RegisterServer2Parameters:
        server = ua.RegisteredServer()
        server.ServerUri = self.server_uri
        server.ProductUri = self.product_uri
        server.ServerNames = [ua.LocalizedText(self.name)]
        server.ServerType = ua.ApplicationType.Server
        server.DiscoveryUrls = list(self.discovery_urls)
        server.IsOnline = online
        mdns = ua.MdnsDiscoveryConfiguration()
        mdns.MdnsServerName = _truncate(self.name, MDNS_NAME_BYTES)
        mdns.ServerCapabilities = list(self.capabilities)
        params = ua.RegisterServer2Parameters()
        params.Server = server
        params.DiscoveryConfiguration = [mdns]
        return params


def _truncate(text: str, limit: int) -> str:
    data = text.encode("utf-8")[:limit]
    return data.decode("utf-8", errors="ignore")


def discovery_url(host: str, port: int) -> str:
    """The URL clients reach this server at: a wildcard address is replaced by the host's name."""
    if host in ("0.0.0.0", "::", "[::]", ""):
        host = socket.getfqdn()
    shown = f"[{host}]" if ":" in host and not host.startswith("[") else host
    return f"opc.tcp://{shown}:{port}/"


async def register(url: str, registrant: Registrant, online: bool, timeout: float) -> list[ua.StatusCode]:
    """One RegisterServer2 call over a secure channel (no session): the configuration results."""
    probe = Client(url, timeout=timeout)
    endpoints = await probe.connect_and_get_server_endpoints()
    chosen = _choose(endpoints)
    if chosen is None:
        offered = sorted({(e.SecurityPolicyUri.rpartition("#")[2], e.SecurityMode.name) for e in endpoints})
        raise ConnectionError(f"it offers no signed channel uacell can open (offered: {offered})")
    policy, endpoint = chosen
    client = Client(url, timeout=timeout)
    client.application_uri = registrant.server_uri  # the channel's certificate is the server's own
    client.name = registrant.name
    server_certificate = first_certificate(endpoint.ServerCertificate)  # its CA's may follow (OPC 10000-6 6.2.6)
    await client.set_security(
        policy,
        str(registrant.certificate),
        str(registrant.private_key),
        server_certificate=server_certificate,
        mode=endpoint.SecurityMode,
    )
    await client.connect_sessionless()
    try:
        results: list[ua.StatusCode] = await client.uaclient.register_server2(registrant.parameters(online))
    finally:
        await client.disconnect_sessionless()
    return results


def _choose(
    endpoints: Sequence[ua.EndpointDescription],
) -> tuple[type[sp.SecurityPolicy], ua.EndpointDescription] | None:
    for mode in MODES:
        for policy in POLICIES:
            for e in endpoints:
                if e.SecurityMode == mode and e.SecurityPolicyUri == policy.URI and e.ServerCertificate:
                    return policy, e
    return None


@dataclass
class DiscoveryConfig:
    """``[discovery]``: where to register ("" = nowhere), how often, which capabilities to announce."""

    url: str = ""
    interval: float = 30.0
    capabilities: list[str] = field(default_factory=lambda: ["DA", "AC", "DI"])


class DiscoveryRegistration:
    """Registers ``registrant`` at ``config.url`` now and every ``config.interval`` seconds until ``stop()``."""

    def __init__(self, config: DiscoveryConfig, registrant: Registrant) -> None:
        self.url = config.url
        self.interval = config.interval
        self.registrant = registrant
        self.timeout = min(config.interval, 10.0)
        self.registered = False  # the last attempt succeeded
        self.attempts = 0  # finished ones, successful or not
        self._background = Background()

    def start(self) -> None:
        self._background.spawn(self._loop(), name="discovery-registration")

    async def _loop(self) -> None:
        while True:
            await self._attempt(online=True)
            await asyncio.sleep(self.interval)

    async def _attempt(self, online: bool) -> bool:
        what = "register with" if online else "unregister from"
        try:
            async with asyncio.timeout(self.timeout + 5.0):
                results = await register(self.url, self.registrant, online, self.timeout)
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # logged, tried again at the next interval; the server runs on
            self.attempts += 1
            reason = str(exc) or type(exc).__name__
            log.warning("could not %s the discovery server %s: %s", what, self.url, reason)
            self.registered = False
            return False
        self.attempts += 1
        refused = [r for r in results if not r.is_good()]
        if refused:  # the registration stands; an mDNS configuration was not taken
            log.info("discovery server %s did not take the mDNS configuration: %s", self.url, refused[0].name)
        if online and not self.registered:
            log.info("registered with the discovery server %s as %s", self.url, self.registrant.server_uri)
        self.registered = online
        return True

    async def stop(self) -> None:
        """Stop registering and unregister (IsOnline false), once."""
        await self._background.close()
        if await self._attempt(online=False):
            log.info("unregistered from the discovery server %s", self.url)
