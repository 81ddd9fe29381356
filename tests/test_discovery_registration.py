"""[discovery]: uacell registers with a Local Discovery Server over a secure channel, and unregisters.

The discovery server is node-opcua's (interop/discovery_server.js), with its PKI in a temporary
directory the test arranges: it trusts uacell's certificate or it does not.
"""

from __future__ import annotations

import asyncio
import logging
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from asyncua import Client, ua
from conftest import NodeServer, ServeProcess, start_serve
from helpers import free_port, wait_until

from uacell.cli.main import main
from uacell.config import load_config
from uacell.core.errors import ConfigError
from uacell.security.pki import PkiPaths
from uacell.services.discovery_registration import DiscoveryConfig, DiscoveryRegistration, Registrant

REGISTRATION = "uacell.services.discovery_registration"


def discovery_server(port: int, pki: Path, log: Path) -> NodeServer:
    """node-opcua's Local Discovery Server (interop/discovery_server.js), its PKI in ``pki``."""
    return NodeServer("discovery_server.js", [str(port), str(pki)], log)


@pytest.fixture
def processes() -> Iterator[list[NodeServer | ServeProcess]]:
    started: list[NodeServer | ServeProcess] = []
    yield started
    for p in reversed(started):
        p.stop()


async def find_servers(url: str) -> dict[str, ua.ApplicationDescription]:
    client = Client(url, timeout=10)
    await client.connect_sessionless()
    try:
        return {s.ApplicationUri: s for s in await client.find_servers()}
    finally:
        await client.disconnect_sessionless()


def own_certificate(data_dir: Path) -> Path:
    """uacell's application certificate, made before the server first starts (`uacell cert renew`)."""
    assert main(["--data-dir", str(data_dir), "cert", "renew"]) == 0
    return PkiPaths.in_data_dir(data_dir).cert


def serve_registering(data_dir: Path, tmp_path: Path, url: str, interval: float) -> ServeProcess:
    config = tmp_path / "uacell.toml"
    config.write_text(f'[discovery]\nurl = "{url}"\ninterval = {interval}\n', encoding="utf-8")
    return start_serve(data_dir, "--config", str(config), "--log-level", "INFO")


@pytest.mark.interop
async def test_uacell_registers_while_it_runs_and_unregisters_at_a_clean_stop(tmp_path, processes):
    data = tmp_path / "data"
    cert = own_certificate(data)
    lds_pki = tmp_path / "lds-pki"
    (lds_pki / "trusted" / "certs").mkdir(parents=True)
    shutil.copy(cert, lds_pki / "trusted" / "certs" / "uacell.der")
    port = free_port()
    url = f"opc.tcp://127.0.0.1:{port}/"
    # The discovery server is not there yet: uacell starts, serves, and tries again at each interval.
    uacell = serve_registering(data, tmp_path, url, 0.3)
    processes.append(uacell)
    application_uri = load_config().server.application_uri
    async with Client(uacell.endpoint, timeout=10) as client:  # serving all along
        state = await client.get_node(ua.ObjectIds.Server_ServerStatus_State).read_value()
        assert state == ua.ServerState.Running
    lds = discovery_server(port, lds_pki, tmp_path / "lds.log")
    processes.append(lds)
    servers: dict[str, ua.ApplicationDescription] = {}

    async def listed() -> bool:
        servers.update(await find_servers(url))
        return application_uri in servers

    deadline = time.monotonic() + 30
    while not await listed():
        assert time.monotonic() < deadline, f"uacell never appeared in FindServers: {list(servers)}"
        await asyncio.sleep(0.1)
    entry = servers[application_uri]
    assert entry.DiscoveryUrls == [uacell.endpoint]
    assert entry.ApplicationType == ua.ApplicationType.Server
    assert entry.ProductUri == "urn:uacell"
    # This discovery server refuses a registration without security (what asyncua's
    # register_to_discovery would do), so uacell's went over a signed channel with its certificate.
    plain = Client(url, timeout=10)
    await plain.connect_sessionless()
    try:
        server = ua.RegisteredServer(
            ServerUri="urn:test:plain",
            ServerNames=[ua.LocalizedText("plain")],
            DiscoveryUrls=["opc.tcp://127.0.0.1:1/"],
            IsOnline=True,
        )
        with pytest.raises(ua.UaStatusCodeError) as refused:
            await plain.uaclient.register_server(server)
        assert refused.value.code == ua.StatusCodes.BadSecurityModeInsufficient
    finally:
        await plain.disconnect_sessionless()

    assert uacell.stop() == 0  # SIGTERM: a clean stop
    assert application_uri not in await find_servers(url)  # unregistered, not timed out
    output = "".join(uacell.output)
    failures = output.count(f"could not register with the discovery server {url}")
    assert failures >= 1  # while it was down
    assert output.index("could not register") < output.index(f"registered with the discovery server {url}")
    assert f"unregistered from the discovery server {url}" in output
    assert list((lds_pki / "rejected").glob("*")) == []


@pytest.mark.interop
async def test_a_discovery_server_that_does_not_trust_uacell_refuses_it_and_uacell_serves_on(tmp_path, processes):
    data = tmp_path / "data"
    cert = own_certificate(data)
    lds_pki = tmp_path / "lds-pki"
    port = free_port()
    url = f"opc.tcp://127.0.0.1:{port}/"
    lds = discovery_server(port, lds_pki, tmp_path / "lds.log")
    processes.append(lds)
    uacell = serve_registering(data, tmp_path, url, 0.3)
    processes.append(uacell)
    # What it refused is uacell's own application certificate (waited for whole: the discovery
    # server may still be writing the file when it appears).
    from cryptography import x509

    def refused_certificate() -> x509.Certificate | None:
        found = list((lds_pki / "rejected").glob("*"))
        if len(found) != 1:
            return None
        try:
            return x509.load_pem_x509_certificate(found[0].read_bytes())
        except ValueError:
            return None

    await wait_until(lambda: refused_certificate() is not None, timeout=30, step=0.05)
    assert refused_certificate() == x509.load_der_x509_certificate(cert.read_bytes())
    assert load_config().server.application_uri not in await find_servers(url)
    async with Client(uacell.endpoint, timeout=10) as client:
        state = await client.get_node(ua.ObjectIds.Server_ServerStatus_State).read_value()
        assert state == ua.ServerState.Running
    assert uacell.stop() == 0
    assert "could not register with the discovery server" in "".join(uacell.output)


async def test_each_failed_attempt_is_one_log_line_and_the_loop_goes_on(tmp_path, caplog):
    """Nothing listens at the URL: every interval one attempt, one warning; stop() unregisters once."""
    registrant = Registrant(
        "urn:test:uacell",
        "urn:uacell",
        "uacell test",
        ["opc.tcp://127.0.0.1:1/"],
        ["DA"],
        tmp_path / "c",
        tmp_path / "k",
    )
    registration = DiscoveryRegistration(DiscoveryConfig(f"opc.tcp://127.0.0.1:{free_port()}/", 0.05), registrant)
    caplog.set_level(logging.INFO, logger=REGISTRATION)
    registration.start()
    await wait_until(lambda: registration.attempts >= 3, timeout=30, step=0.01)
    await registration.stop()
    lines = [r for r in caplog.records if r.name == REGISTRATION]
    assert len(lines) == registration.attempts
    assert all(r.levelno == logging.WARNING for r in lines)
    assert sum("could not unregister" in r.getMessage() for r in lines) == 1
    assert not registration.registered


def test_the_discovery_section_is_checked(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text('[discovery]\nurl = "http://lds:4840/"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"\[discovery\] url: must look like opc.tcp://"):
        load_config(config)
    config.write_text('[discovery]\nurl = "opc.tcp://lds:4840/"\ninterval = 0\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"\[discovery\] interval: must be a positive number"):
        load_config(config)
    config.write_text('[discovery]\nurl = "opc.tcp://lds:4840/"\ncapabilities = ["DA"]\n', encoding="utf-8")
    loaded = load_config(config)
    assert (loaded.discovery.url, loaded.discovery.interval, loaded.discovery.capabilities) == (
        "opc.tcp://lds:4840/",
        30.0,
        ["DA"],
    )
