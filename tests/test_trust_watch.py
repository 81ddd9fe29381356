"""Decision 100 through real asyncua clients over TCP: the open secure channels follow the trust list's
files when an administrator changes them with ``uacell cert`` in another process, and when a CA's
revocation list passes its nextUpdate (RFC 5280 5.1.2.5, 6.3.3) while a client is connected. The CAs,
certificates and lists come from tests/plant_ca.py (built from RFC 5280), not from uacell."""

from __future__ import annotations

import asyncio
import datetime as dt
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import secure_client
from plant_ca import Authority
from test_push_certificates import gds_session, plant, reaches

from uacell.security.pki import PkiPaths

pytestmark = pytest.mark.asyncio(loop_scope="module")

__all__ = ["plant"]  # the plant's server, GDS and CAs, as tests/test_push_certificates.py sets them up
_GROUP = "ServerConfiguration_CertificateGroups_DefaultApplicationGroup"
LAST_UPDATE = ua.NodeId(getattr(ua.ObjectIds, f"{_GROUP}_TrustList_LastUpdateTime"))
WATCH_TIMEOUT = 20.0  # the server looks once a second; generous for a loaded machine


def uacell_cert(data_dir: Path, *args: str) -> str:
    """``uacell cert ARGS`` on the server's data directory, from another process, as an administrator runs it."""
    done = subprocess.run(
        [sys.executable, "-m", "uacell", "cert", *args, "--data-dir", str(data_dir)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


async def connected(endpoint: str, directory: Path, cert: Any, key: Any, uri: str) -> Client:
    directory.mkdir(exist_ok=True)
    client = await secure_client(endpoint, directory, cert, key, uri)
    await client.connect()
    return client


def files_changed_at(paths: PkiPaths) -> dt.datetime:
    """The latest change of the three folders, as the file system tells it."""
    latest = max(folder.stat().st_mtime for folder in (paths.trusted, paths.issuers, paths.crl))
    return dt.datetime.fromtimestamp(latest, dt.UTC)


async def published(client: Client, at: dt.datetime) -> dt.datetime:
    """Wait until the TrustList's LastUpdateTime says ``at`` (to the millisecond) or later; returns it."""
    node, deadline = client.get_node(LAST_UPDATE), asyncio.get_running_loop().time() + WATCH_TIMEOUT
    while True:
        value: dt.datetime = await node.read_value()
        if value.replace(tzinfo=dt.UTC) >= at - dt.timedelta(milliseconds=1):
            return value
        assert asyncio.get_running_loop().time() < deadline, f"LastUpdateTime stayed at {value}, not {at}"
        await asyncio.sleep(0.1)


async def until_closed(client: Client) -> ua.StatusCode | None:
    """Read the server's state until the channel is gone; what the client was told (None: the
    connection simply ended)."""
    deadline = asyncio.get_running_loop().time() + WATCH_TIMEOUT
    while asyncio.get_running_loop().time() < deadline:
        try:
            await client.nodes.server_state.read_value()
        except ua.UaStatusCodeError as err:
            return ua.StatusCode(err.code)
        except (ua.UaError, ConnectionError, TimeoutError):
            return None
        await asyncio.sleep(0.1)
    raise AssertionError(f"the channel was still open after {WATCH_TIMEOUT} s")


async def test_a_ca_removed_with_uacell_cert_closes_the_channels_it_admitted(
    plant: dict[str, Any], tmp_path: Path
) -> None:
    """``uacell cert remove`` of a contractor's CA, run while the server is up: its laptop's open channel is
    closed, a new one is refused, the GDS's channel (another CA) goes on, and the TrustList's
    LastUpdateTime moves (OPC 10000-12 7.8.2.1) as it does for a GDS's own changes."""
    app, paths = plant["app"], plant["paths"]
    contractor = Authority.root("Contractor CA", key_index=4)
    laptop, laptop_key = contractor.application("urn:contractor:laptop", "Laptop", key_index=5)
    ca_file, crl_file = tmp_path / "contractor.der", tmp_path / "contractor.crl"
    ca_file.write_bytes(contractor.der)
    crl_file.write_bytes(contractor.crl())
    uacell_cert(app.data_dir, "trust", str(ca_file))
    uacell_cert(app.data_dir, "crl", str(crl_file))
    admin = await gds_session(plant, tmp_path)
    laptop_client = await connected(app.endpoint, tmp_path / "laptop", laptop, laptop_key, "urn:contractor:laptop")
    try:
        assert await laptop_client.nodes.server_state.read_value() == ua.ServerState.Running
        trusted_at = await published(admin, files_changed_at(paths))  # the watch has seen the additions

        out = uacell_cert(app.data_dir, "remove", str(ca_file))
        assert "removed" in out and not any(p.read_bytes() == contractor.der for p in paths.trusted.iterdir())
        await until_closed(laptop_client)
        assert not await reaches(app.endpoint, tmp_path, laptop, laptop_key, "urn:contractor:laptop")
        assert await admin.nodes.server_state.read_value() == ua.ServerState.Running  # another CA's: kept
        removed_at = files_changed_at(paths)
        assert removed_at > trusted_at.replace(tzinfo=dt.UTC)
        await published(admin, removed_at)
    finally:
        await admin.disconnect()
        await asyncio.gather(laptop_client.disconnect(), return_exceptions=True)


async def test_a_revocation_list_that_goes_stale_closes_the_channels_it_vouched_for(
    plant: dict[str, Any], tmp_path: Path
) -> None:
    """Decision 98 while a client is connected: the contractor's list is due for renewal a few seconds
    after the laptop connects. Once nextUpdate passes, the laptop's channel is closed and a new one is
    refused (the revocation is unknown); the CA's renewed list, added with ``uacell cert crl``, lets it
    in again. The GDS, whose CA's lists are current, is not touched."""
    app, paths = plant["app"], plant["paths"]
    contractor = Authority.root("Contractor Two CA", key_index=6)
    laptop, laptop_key = contractor.application("urn:contractor:two", "Laptop two", key_index=7)
    (paths.trusted / "contractor-two.der").write_bytes(contractor.der)
    due = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=6)
    (paths.crl / "contractor-two.crl").write_bytes(contractor.crl(next_update=due))
    admin = await gds_session(plant, tmp_path)
    laptop_client = await connected(app.endpoint, tmp_path / "laptop", laptop, laptop_key, "urn:contractor:two")
    try:
        assert dt.datetime.now(dt.UTC) < due, "the machine was too slow to connect before the list's nextUpdate"
        await until_closed(laptop_client)
        assert dt.datetime.now(dt.UTC) >= due.replace(microsecond=0)  # not before the list was due
        assert not await reaches(app.endpoint, tmp_path, laptop, laptop_key, "urn:contractor:two")
        assert await admin.nodes.server_state.read_value() == ua.ServerState.Running

        renewed = tmp_path / "renewed.crl"
        renewed.write_bytes(contractor.crl())
        uacell_cert(app.data_dir, "crl", str(renewed))
        assert await reaches(app.endpoint, tmp_path, laptop, laptop_key, "urn:contractor:two")
    finally:
        await admin.disconnect()
        await asyncio.gather(laptop_client.disconnect(), return_exceptions=True)


async def test_a_change_that_admits_everyone_it_did_closes_nothing(plant: dict[str, Any], tmp_path: Path) -> None:
    """A change of the files that still admits a connected client (another CA's list renewed, an issuer
    added) leaves its channel open: the watch closes what the new files refuse, nothing else."""
    paths = plant["paths"]
    admin = await gds_session(plant, tmp_path)
    try:
        other = Authority.root("Unrelated CA", key_index=8)
        (paths.issuers / "unrelated.der").write_bytes(other.der)
        (paths.crl / "unrelated.crl").write_bytes(other.crl())
        await published(admin, files_changed_at(paths))  # the watch has looked at the change
        assert await admin.nodes.server_state.read_value() == ua.ServerState.Running
    finally:
        await admin.disconnect()


async def test_the_watch_stops_with_the_server(tmp_path: Path) -> None:
    """The watch is a task of the server: a stopped server leaves none behind."""
    others = {t for t in asyncio.all_tasks() if t.get_name() == "uacell-trust-watch"}  # the module's server's
    app = await start_app(fast_config(tmp_path / "data"))
    ours = [t for t in asyncio.all_tasks() if t.get_name() == "uacell-trust-watch" and t not in others]
    assert len(ours) == 1 and not ours[0].done()
    await app.stop()
    assert ours[0].done()
