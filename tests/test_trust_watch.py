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
from cryptography.hazmat.primitives import serialization
from helpers import Collector, secure_client, session_on_new_channel
from plant_ca import Authority
from test_push_certificates import gds_session, plant, reaches

from uacell.security.pki import PkiPaths, trust_stamp

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


async def moved_to_new_channel(old: Client, endpoint: str, directory: Path, cert: Any, key: Any, uri: str) -> Client:
    """A new secure channel with the same certificate, on which the client activates ``old``'s session."""
    directory.mkdir(exist_ok=True)
    client = await secure_client(endpoint, directory, cert, key, uri)
    return await session_on_new_channel(client, old.uaclient.protocol.authentication_token, old._server_nonce)


class _Quiet:
    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        pass


async def test_a_session_whose_certificate_was_removed_cannot_move_to_a_new_channel(
    plant: dict[str, Any], tmp_path: Path
) -> None:
    """Decision 104: once the trust list no longer admits a client, its session goes on over no new channel
    either. A session with a subscription outlives its connection (OPC 10000-4 6.7), and the new channel's
    ActivateSession compared the certificate with the session's without asking the trust list: a removed
    client came straight back, the way node-opcua reconnects."""
    app, paths = plant["app"], plant["paths"]
    contractor = Authority.root("Contractor Three CA", key_index=9)
    laptop, laptop_key = contractor.application("urn:contractor:three", "Laptop three", key_index=10)
    ca_file = tmp_path / "contractor.der"
    ca_file.write_bytes(contractor.der)
    (paths.trusted / "contractor-three.der").write_bytes(contractor.der)
    (paths.crl / "contractor-three.crl").write_bytes(contractor.crl())
    laptop_client = await connected(app.endpoint, tmp_path / "laptop", laptop, laptop_key, "urn:contractor:three")
    moved: Client | None = None
    try:
        subscription = await laptop_client.create_subscription(100, _Quiet())
        await subscription.subscribe_data_change(laptop_client.nodes.server_state)
        # trusted: the session moves to a new channel and goes on there
        moved = await moved_to_new_channel(
            laptop_client, app.endpoint, tmp_path / "moved", laptop, laptop_key, "urn:contractor:three"
        )
        assert await moved.nodes.server_state.read_value() == ua.ServerState.Running

        uacell_cert(app.data_dir, "remove", str(ca_file))
        await until_closed(moved)  # the channel the session moved to is checked again, as its first was
        with pytest.raises(ua.UaStatusCodeError) as refused:
            await moved_to_new_channel(
                moved, app.endpoint, tmp_path / "again", laptop, laptop_key, "urn:contractor:three"
            )
        assert refused.value.code == ua.StatusCodes.BadSecurityChecksFailed
    finally:
        if moved is not None:
            moved.disconnect_socket()
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


async def test_a_client_certificate_that_expires_closes_its_channel(plant: dict[str, Any], tmp_path: Path) -> None:
    """Decision 104: a client's own certificate reaching its notAfter (RFC 5280 4.1.2.5) while its channel
    is open closes the channel within the watch's second, as the files' own dates do (decision 100);
    the same certificate then gets no new channel and session (Bad_CertificateTimeInvalid)."""
    app, paths = plant["app"], plant["paths"]
    contractor = Authority.root("Contractor Four CA", key_index=11)
    ends = (dt.datetime.now(dt.UTC) + dt.timedelta(seconds=6)).replace(microsecond=0)  # a DER time: whole seconds
    laptop, laptop_key = contractor.application("urn:contractor:four", "Laptop four", key_index=12, not_after=ends)
    (paths.trusted / "contractor-four.der").write_bytes(contractor.der)
    (paths.crl / "contractor-four.crl").write_bytes(contractor.crl())
    admin = await gds_session(plant, tmp_path)
    laptop_client = await connected(app.endpoint, tmp_path / "laptop", laptop, laptop_key, "urn:contractor:four")
    try:
        assert dt.datetime.now(dt.UTC) < ends, "the machine was too slow to connect before the certificate ended"
        await until_closed(laptop_client)
        assert dt.datetime.now(dt.UTC) >= ends  # not before it ended
        assert not await reaches(app.endpoint, tmp_path, laptop, laptop_key, "urn:contractor:four")
        assert await admin.nodes.server_state.read_value() == ua.ServerState.Running  # a valid one: kept
    finally:
        await admin.disconnect()
        await asyncio.gather(laptop_client.disconnect(), return_exceptions=True)


async def channel_events(admin: Client) -> Collector:
    """The admin session's subscription to the Server object's AuditOpenSecureChannel events."""
    seen = Collector()
    subscription = await admin.create_subscription(0, seen)
    await subscription.subscribe_events(
        admin.nodes.server, [admin.get_node(ua.NodeId(ua.ObjectIds.AuditOpenSecureChannelEventType))]
    )
    return seen


async def test_a_renewal_is_audited_and_verifies_the_certificate_again(
    plant: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Decision 104, OPC 10000-4 6.1.7: "ApplicationInstanceCertificates verification shall be executed
    every time the SecurityToken is renewed for a SecureChannel", and OPC 10000-5 6.4.6's
    AuditOpenSecureChannelEvent is fired for a renewal as for an opening (RequestType Renew). The watch is
    made to look away for the second part, so that the renewal alone finds the CA removed."""
    app, paths = plant["app"], plant["paths"]
    contractor = Authority.root("Contractor Five CA", key_index=13)
    laptop, laptop_key = contractor.application("urn:contractor:five", "Laptop five", key_index=14)
    (paths.trusted / "contractor-five.der").write_bytes(contractor.der)
    (paths.crl / "contractor-five.crl").write_bytes(contractor.crl())
    admin = await gds_session(plant, tmp_path)
    seen = await channel_events(admin)
    laptop_client = await connected(app.endpoint, tmp_path / "laptop", laptop, laptop_key, "urn:contractor:five")
    try:
        channel = str(laptop_client.uaclient.protocol._connection.security_token.ChannelId)
        await laptop_client.open_secure_channel(renew=True)
        assert await laptop_client.nodes.server_state.read_value() == ua.ServerState.Running

        def renewal(e: Any) -> bool:
            return bool(e.RequestType == ua.SecurityTokenRequestType.Renew and e.SecureChannelId == channel)

        renewed = await seen.wait_for(renewal)
        assert renewed.Status is True
        assert renewed.StatusCodeId == ua.StatusCode(ua.StatusCodes.Good)
        assert renewed.ClientUserId == "System/OpenSecureChannel"
        assert renewed.ClientCertificate == laptop.public_bytes(serialization.Encoding.DER)
        assert renewed.SecurityMode == ua.MessageSecurityMode.SignAndEncrypt
        assert renewed.RequestedLifetime > 0
        seen.clear()

        await published(admin, files_changed_at(paths))  # the watch has seen the files as they are
        frozen = trust_stamp(paths)
        monkeypatch.setattr("uacell.security.policy.trust_stamp", lambda _paths: frozen)  # and now looks away
        (paths.trusted / "contractor-five.der").unlink()
        with pytest.raises((ua.UaError, ConnectionError, TimeoutError)):
            await laptop_client.open_secure_channel(renew=True)
        refused = await seen.wait_for(renewal)
        assert refused.Status is False
        # the chain's issuer is gone: what a client is told about a chain (decision 92)
        assert refused.StatusCodeId == ua.StatusCode(ua.StatusCodes.BadSecurityChecksFailed)
        assert await until_closed(laptop_client) in (None, ua.StatusCode(ua.StatusCodes.BadSecurityChecksFailed))
        assert await admin.nodes.server_state.read_value() == ua.ServerState.Running
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
