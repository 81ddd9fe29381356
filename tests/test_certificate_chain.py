"""Client certificates issued by a plant's CA (OPC 10000-4 6.1.3, OPC 10000-6 6.2.6, decision 92):
chains built to a trusted certificate through issuers the client sent or the administrator put in
pki/issuers/, revocation lists in pki/crl/; pure, through the trust list's files, and over TCP."""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.common.utils import ServiceError
from conftest import fast_config, start_app
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from helpers import secure_client
from plant_ca import Authority, application_certificate, der, pem, signed_with_sha1

from uacell.security.chain import Anchors, check_chain, next_change, split_chain
from uacell.security.pki import CertificateValidator, PkiPaths, TrustList, told, trust_stamp
from uacell.server import UacellServer

ON_SERVER_LOOP = pytest.mark.asyncio(loop_scope="module")  # the tests that use the module's server
S = ua.StatusCodes
MES = "urn:plant:line3:mes"


@pytest.fixture(scope="module")
def ca() -> Iterator[dict[str, Any]]:
    """Root -> issuing CA -> the MES client; a second client the issuing CA revoked."""
    root = Authority.root()
    issuing = root.intermediate()
    leaf, key = issuing.application(MES)
    revoked, revoked_key = issuing.application("urn:plant:line3:old-mes", "Old MES", key_index=3)
    issuing.revoke(revoked)
    yield {"root": root, "issuing": issuing, "leaf": leaf, "key": key, "revoked": revoked, "revoked_key": revoked_key}


def crls(*authorities: Authority) -> tuple[x509.CertificateRevocationList, ...]:
    return tuple(x509.load_der_x509_crl(a.crl()) for a in authorities)


def now() -> dt.datetime:
    """The time of the check: the CAs are made when the tests that use them start (a module-level "now"
    is from collection, which a slow run puts minutes before the certificates' notBefore)."""
    return dt.datetime.now(dt.UTC)


# the chain's steps, pure ------------------------------------------------------------------------------


def test_a_chain_is_split_by_the_lengths_in_its_der(ca: dict[str, Any]) -> None:
    leaf, issuing, root = ca["leaf"], ca["issuing"], ca["root"]
    assert split_chain(der(leaf)) == [leaf]
    assert split_chain(der(leaf) + issuing.der + root.der) == [leaf, issuing.cert, root.cert]
    for bad in (b"", b"junk", (der(leaf) + issuing.der)[:-10], der(leaf) + b"\x30"):
        with pytest.raises(ValueError):
            split_chain(bad)


def test_a_chain_to_a_trusted_root_through_an_issuer_the_client_sent(ca: dict[str, Any]) -> None:
    root, issuing, leaf = ca["root"], ca["issuing"], ca["leaf"]
    anchors = Anchors(trusted=(root.cert,), crls=crls(root, issuing))
    assert check_chain([leaf, issuing.cert], anchors, now()) is None
    # the same issuer from pki/issuers/ instead
    assert (
        check_chain([leaf], Anchors(trusted=(root.cert,), issuers=(issuing.cert,), crls=crls(root, issuing)), now())
        is None
    )
    # trusting the issuing CA alone trusts what it issued; the root must still be found to end the chain
    only_issuing = Anchors(trusted=(issuing.cert,), issuers=(root.cert,), crls=crls(root, issuing))
    assert check_chain([leaf], only_issuing, now()) is None


def test_each_step_answers_its_own_code(ca: dict[str, Any]) -> None:
    root, issuing, leaf = ca["root"], ca["issuing"], ca["leaf"]
    full = crls(root, issuing)

    def code(chain: list[x509.Certificate], anchors: Anchors, **kw: Any) -> int | None:
        refusal = check_chain(chain, anchors, now(), **kw)
        return None if refusal is None else refusal.code

    # the issuer is nowhere: the chain cannot be built
    assert code([leaf], Anchors(trusted=(root.cert,), crls=full)) == S.BadCertificateChainIncomplete
    # built, but nothing of it is trusted
    assert code([leaf, issuing.cert], Anchors(issuers=(root.cert,), crls=full)) == S.BadCertificateUntrusted
    # an impostor with the issuing CA's name and another key: the signature does not verify
    impostor = root.intermediate(key_index=4)
    assert code([leaf, impostor.cert], Anchors(trusted=(root.cert,), crls=full)) == S.BadCertificateInvalid
    # the issuing CA's revocation list is missing: the leaf's revocation is unknown; the root's: the issuer's
    assert (
        code([leaf, issuing.cert], Anchors(trusted=(root.cert,), crls=crls(root))) == S.BadCertificateRevocationUnknown
    )
    assert (
        code([leaf, issuing.cert], Anchors(trusted=(root.cert,), crls=crls(issuing)))
        == S.BadCertificateIssuerRevocationUnknown
    )
    assert code([leaf, issuing.cert], Anchors(trusted=(root.cert,)), require_crls=False) is None
    # a revocation list signed by another key counts as none
    forged = (x509.load_der_x509_crl(issuing.crl(signer=impostor.key)), *crls(root))
    assert code([leaf, issuing.cert], Anchors(trusted=(root.cert,), crls=forged)) == S.BadCertificateRevocationUnknown
    # revoked: the client's own certificate, then its issuer
    assert code([ca["revoked"], issuing.cert], Anchors(trusted=(root.cert,), crls=full)) == S.BadCertificateRevoked
    root2 = Authority.root("Plant Root CA 2", key_index=5)
    issuing2 = root2.intermediate("Plant Issuing CA 2", key_index=6)
    leaf2, _ = issuing2.application(MES, key_index=7)
    root2.revoke(issuing2.cert)
    assert (
        code([leaf2, issuing2.cert], Anchors(trusted=(root2.cert,), crls=crls(root2, issuing2)))
        == S.BadCertificateIssuerRevoked
    )


def test_a_revocation_list_past_its_next_update_says_nothing_but_revocations(ca: dict[str, Any]) -> None:
    """RFC 5280 6.3.3 (and OPC 10000-4's revocation check): a list whose nextUpdate has passed does not say
    whether a certificate was revoked since, so the revocation is unknown; what it lists stays revoked."""
    root, issuing, leaf = ca["root"], ca["issuing"], ca["leaf"]
    long_ago = now() - dt.timedelta(days=8)  # plant_ca's lists are due a week after they were issued
    stale_issuing = x509.load_der_x509_crl(issuing.crl(issued=long_ago))
    stale_root = x509.load_der_x509_crl(root.crl(issued=long_ago))
    fresh_root, fresh_issuing = crls(root, issuing)
    trusted = (root.cert,)

    def refusal(chain: list[x509.Certificate], *lists: x509.CertificateRevocationList, **kw: Any) -> Any:
        return check_chain(chain, Anchors(trusted=trusted, crls=lists), now(), **kw)

    stale = refusal([leaf, issuing.cert], fresh_root, stale_issuing)
    assert stale is not None and stale.code == S.BadCertificateRevocationUnknown
    assert "was due to be renewed" in stale.why and "Plant Issuing CA" in stale.why
    stale_above = refusal([leaf, issuing.cert], stale_root, fresh_issuing)
    assert stale_above is not None and stale_above.code == S.BadCertificateIssuerRevocationUnknown
    assert refusal([leaf, issuing.cert], fresh_root, fresh_issuing, stale_issuing) is None  # the newest counts
    assert refusal([leaf, issuing.cert], stale_root, stale_issuing, require_crls=False) is None
    revoked = refusal([ca["revoked"], issuing.cert], fresh_root, stale_issuing, require_crls=False)
    assert revoked is not None and revoked.code == S.BadCertificateRevoked  # stale, still a revocation
    revoked = refusal([ca["revoked"], issuing.cert], fresh_root, stale_issuing)
    assert revoked is not None and revoked.code == S.BadCertificateRevoked


def test_the_next_instant_the_same_files_judge_otherwise(ca: dict[str, Any]) -> None:
    """Decision 100: when check_chain's answer may change with time alone: the earliest nextUpdate of a
    revocation list (RFC 5280 5.1.2.5), or the start or end of a trusted or issuer certificate's
    validity (5.1.2.5 of certificates), after the instant asked about."""
    root, issuing, leaf = ca["root"], ca["issuing"], ca["leaf"]
    at = now()
    soon = at + dt.timedelta(seconds=30)
    later = at + dt.timedelta(days=2)
    lists = (
        x509.load_der_x509_crl(root.crl(next_update=later)),
        x509.load_der_x509_crl(issuing.crl(next_update=soon)),
    )
    anchors = Anchors(trusted=(root.cert,), issuers=(issuing.cert,), crls=lists)
    assert next_change(anchors, at) == soon.replace(microsecond=0)  # a DER time has whole seconds
    assert check_chain([leaf, issuing.cert], anchors, at) is None
    after = next_change(anchors, soon + dt.timedelta(seconds=1))
    assert after == later.replace(microsecond=0)
    stale = check_chain([leaf, issuing.cert], anchors, soon + dt.timedelta(seconds=1))
    assert stale is not None and stale.code == S.BadCertificateRevocationUnknown  # what the instant changed
    # past every list, the CAs' notAfter is what comes next; nothing at all, nothing ahead
    assert next_change(anchors, later + dt.timedelta(seconds=1)) == min(
        root.cert.not_valid_after_utc, issuing.cert.not_valid_after_utc
    )
    not_yet = root.intermediate("Next Year CA", key_index=6, not_before=at + dt.timedelta(days=1))
    assert next_change(Anchors(issuers=(not_yet.cert,)), at) == not_yet.cert.not_valid_before_utc
    assert next_change(Anchors(), at) is None


def test_the_trust_stamp_tells_any_change_of_the_files(tmp_path: Path, ca: dict[str, Any]) -> None:
    """Decision 100: a file added, rewritten or removed in trusted/, issuers/ or crl/ changes the stamp the
    server compares once a second; rejected/ and a look with no change do not."""
    paths = PkiPaths.in_data_dir(tmp_path)
    assert trust_stamp(paths) == ()  # no folders yet
    paths.create()
    empty = trust_stamp(paths)
    (paths.trusted / "root.der").write_bytes(der(ca["root"].cert))
    added = trust_stamp(paths)
    assert added != empty and trust_stamp(paths) == added
    (paths.rejected / "other.der").write_bytes(der(ca["leaf"]))
    assert trust_stamp(paths) == added
    crl = paths.crl / "issuing.crl"
    crl.write_bytes(ca["issuing"].crl())
    with_crl = trust_stamp(paths)
    crl.write_bytes(ca["issuing"].crl() + b"")  # rewritten: a new modification time
    os.utime(crl, ns=(1, 1))
    assert trust_stamp(paths) not in (with_crl, added)
    crl.unlink()
    assert trust_stamp(paths) == added
    (paths.trusted / "root.der").unlink()
    (paths.issuers / "root.der").write_bytes(der(ca["root"].cert))  # the same file, another list
    assert trust_stamp(paths) not in (added, empty)


def test_the_security_policy_check(ca: dict[str, Any]) -> None:
    """OPC 10000-4 6.1.3's Security Policy Check for the policies uacell offers (OPC 10000-7: Basic256Sha256,
    Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss): an application's key is RSA of 2048 to 4096 bits, and
    every certificate of the chain, the root's own included, is signed with SHA-256 or a longer hash;
    Bad_CertificatePolicyCheckFailed otherwise, before the trust list is looked at."""
    root, issuing = ca["root"], ca["issuing"]
    anchors = Anchors(trusted=(root.cert,), crls=crls(root, issuing))

    def refusal(chain: list[x509.Certificate], with_anchors: Anchors = anchors) -> Any:
        return check_chain(chain, with_anchors, now())

    assert refusal([ca["leaf"], issuing.cert]) is None  # RSA 2048, SHA-256 throughout
    small_key = rsa.generate_private_key(public_exponent=65537, key_size=1024)
    small, _ = issuing.application("urn:plant:old-hmi", "Old HMI", key=small_key)
    weak = refusal([small, issuing.cert])
    assert weak is not None and weak.code == S.BadCertificatePolicyCheckFailed and weak.certificate == small
    assert "1024" in weak.why
    big_key = rsa.generate_private_key(public_exponent=65537, key_size=4104)
    big, _ = issuing.application("urn:plant:big", "Big", key=big_key)
    too_big = refusal([big, issuing.cert])
    assert too_big is not None and too_big.code == S.BadCertificatePolicyCheckFailed and "4104" in too_big.why
    sha1_leaf = signed_with_sha1(ca["leaf"], issuing.key)
    old = refusal([sha1_leaf, issuing.cert])
    assert old is not None and old.code == S.BadCertificatePolicyCheckFailed and "SHA1" in old.why.upper()
    sha1_issuing = signed_with_sha1(issuing.cert, root.key)
    above = refusal([ca["leaf"], sha1_issuing])
    assert above is not None and above.code == S.BadCertificatePolicyCheckFailed and above.certificate == sha1_issuing
    # before the trust list: an untrusted weak certificate is told what is wrong with it, not that it is untrusted
    lone = application_certificate("urn:plant:lone", "Lone", small_key)
    untrusted = refusal([lone], Anchors())
    assert untrusted is not None and untrusted.code == S.BadCertificatePolicyCheckFailed
    # a certificate trusted by itself (decision 92's pinning) is checked too
    assert refusal([lone], Anchors(trusted=(lone,))).code == S.BadCertificatePolicyCheckFailed
    strong = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    sha1_self = signed_with_sha1(application_certificate("urn:plant:self", "Self", strong), strong)
    assert refusal([sha1_self], Anchors(trusted=(sha1_self,))).code == S.BadCertificatePolicyCheckFailed


def test_an_issuer_must_be_a_valid_ca(ca: dict[str, Any]) -> None:
    root = ca["root"]
    not_a_ca = root.intermediate("Not a CA", key_index=4, ca=False)
    leaf, _ = not_a_ca.application(MES, key_index=7)
    anchors = Anchors(trusted=(root.cert,), crls=crls(root, not_a_ca))
    refusal = check_chain([leaf, not_a_ca.cert], anchors, now())
    assert refusal is not None and refusal.code == S.BadCertificateIssuerUseNotAllowed
    assert refusal.certificate == not_a_ca.cert
    expired = root.intermediate("Expired CA", key_index=6, not_before=now() - dt.timedelta(days=20), days=10)
    leaf, _ = expired.application(MES, key_index=7)
    refusal = check_chain([leaf, expired.cert], Anchors(trusted=(root.cert,), crls=crls(root, expired)), now())
    assert refusal is not None and refusal.code == S.BadCertificateIssuerTimeInvalid


def test_a_certificate_trusted_by_itself(ca: dict[str, Any]) -> None:
    root, issuing, leaf = ca["root"], ca["issuing"], ca["leaf"]
    # its issuer unknown: trusted as pinned, as before chains were checked
    assert check_chain([leaf], Anchors(trusted=(leaf,)), now()) is None
    # its issuer known: the chain counts, revocation included; a missing list alone does not refuse it
    assert (
        check_chain([ca["revoked"]], Anchors(trusted=(ca["revoked"],), issuers=(issuing.cert, root.cert)), now())
        is None
    )
    anchors = Anchors(trusted=(ca["revoked"],), issuers=(issuing.cert, root.cert), crls=crls(root, issuing))
    refusal = check_chain([ca["revoked"]], anchors, now())
    assert refusal is not None and refusal.code == S.BadCertificateRevoked


def test_what_the_client_is_told() -> None:
    for own in (S.BadCertificateUntrusted, S.BadCertificateTimeInvalid, S.BadCertificateUriInvalid):
        assert told(own) == own
    for chain in (
        S.BadCertificateChainIncomplete,
        S.BadCertificateInvalid,
        S.BadCertificateIssuerTimeInvalid,
        S.BadCertificateIssuerUseNotAllowed,
        S.BadCertificateRevocationUnknown,
        S.BadCertificateIssuerRevocationUnknown,
        S.BadCertificateRevoked,
        S.BadCertificateIssuerRevoked,
    ):
        assert told(chain) == S.BadSecurityChecksFailed


# the trust list's files --------------------------------------------------------------------------------


def install(
    paths: PkiPaths, *, trusted: Sequence[bytes], issuers: Sequence[bytes] = (), crl: Sequence[bytes] = ()
) -> None:
    paths.create()
    for i, data in enumerate(trusted):
        (paths.trusted / f"t{i}.der").write_bytes(data)
    for i, data in enumerate(issuers):
        (paths.issuers / f"i{i}.der").write_bytes(data)
    for i, data in enumerate(crl):
        (paths.crl / f"c{i}.crl").write_bytes(data)


def test_the_files_decide_and_the_log_says_what_to_do(
    tmp_path: Path, ca: dict[str, Any], caplog: pytest.LogCaptureFixture
) -> None:
    root, issuing, leaf = ca["root"], ca["issuing"], ca["leaf"]
    paths = PkiPaths.in_data_dir(tmp_path)
    trust = TrustList(paths)
    for d in (paths.issuers, paths.crl):
        assert d.is_dir()
    install(paths, trusted=[root.der])
    caplog.set_level(logging.INFO, logger="uacell.security.policy")  # refusals are logged there, rate-limited
    refusal = trust.refusal([leaf], MES)
    assert refusal is not None and refusal.code == S.BadCertificateChainIncomplete
    [rejected] = paths.rejected.iterdir()  # trusting it by itself is one way out: it waits in rejected/
    assert rejected.read_bytes() == der(leaf)
    assert str(paths.issuers) in caplog.text and str(paths.crl) in caplog.text and str(rejected) in caplog.text
    # the issuing CA's certificate in PEM, the root's CRL in PEM, the issuing CA's in DER
    (paths.issuers / "issuing.pem").write_bytes(pem(issuing.cert))
    (paths.crl / "root.crl").write_bytes(_pem_crl(root))
    caplog.clear()
    refusal = trust.refusal([leaf], MES)
    assert refusal is not None and refusal.code == S.BadCertificateRevocationUnknown
    assert f"Put the CA's revocation list into {paths.crl}/" in caplog.text
    (paths.crl / "issuing.crl").write_bytes(issuing.crl())
    (paths.crl / "junk.crl").write_bytes(b"not a list")  # ignored, logged
    assert trust.refusal([leaf], MES) is None
    assert "ignoring" in caplog.text and "junk.crl" in caplog.text
    refusal = trust.refusal(der(ca["revoked"]), "urn:plant:line3:old-mes")  # DER bytes as a client sends them
    assert refusal is not None and refusal.code == S.BadCertificateRevoked
    assert [p.read_bytes() for p in paths.rejected.iterdir()] == [der(leaf)]  # a revoked one is not offered


def _pem_crl(authority: Authority) -> bytes:
    return x509.load_der_x509_crl(authority.crl()).public_bytes(serialization.Encoding.PEM)


def test_trust_on_first_use_trusts_only_what_trusting_would_let_in(tmp_path: Path, ca: dict[str, Any]) -> None:
    root, issuing = ca["root"], ca["issuing"]
    paths = PkiPaths.in_data_dir(tmp_path)
    install(paths, trusted=[], issuers=[issuing.der, root.der], crl=[root.crl(), issuing.crl()])
    trust = TrustList(paths, trust_on_first_use=True)
    assert trust.admit([ca["leaf"]], MES) is True
    assert [p.read_bytes() for p in paths.trusted.iterdir()] == [der(ca["leaf"])]
    assert trust.admit([ca["revoked"]], "urn:plant:line3:old-mes") is False  # revoked stays refused
    assert [p.read_bytes() for p in paths.trusted.iterdir()] == [der(ca["leaf"])]
    assert list(paths.rejected.iterdir()) == []


def test_revocation_lists_may_be_optional(tmp_path: Path, ca: dict[str, Any]) -> None:
    paths = PkiPaths.in_data_dir(tmp_path)
    install(paths, trusted=[ca["root"].der], issuers=[ca["issuing"].der])
    assert TrustList(paths).admit([ca["leaf"]], MES) is False
    assert TrustList(paths, require_revocation_lists=False).admit([ca["leaf"]], MES) is True


async def test_the_validator_tells_the_client_less_than_the_log(tmp_path: Path, ca: dict[str, Any]) -> None:
    paths = PkiPaths.in_data_dir(tmp_path)
    install(paths, trusted=[ca["root"].der], issuers=[ca["issuing"].der], crl=[ca["root"].crl(), ca["issuing"].crl()])
    validate = CertificateValidator(TrustList(paths))
    desc = ua.ApplicationDescription(
        ApplicationUri="urn:plant:line3:old-mes", ApplicationType=ua.ApplicationType.Client
    )
    verdict = validate.check([ca["revoked"]], desc.ApplicationUri)
    assert verdict is not None
    assert (verdict.told, verdict.precise) == (S.BadSecurityChecksFailed, S.BadCertificateRevoked)
    assert verdict.certificate == der(ca["revoked"])
    with pytest.raises(ServiceError) as info:  # as asyncua's certificate validator
        await validate(ca["revoked"], desc)
    assert info.value.code == S.BadSecurityChecksFailed
    desc.ApplicationUri = MES
    assert validate.check([ca["leaf"]], desc.ApplicationUri) is None


# over TCP, an asyncua client with a CA's certificate ----------------------------------------------------


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def server(tmp_path_factory: pytest.TempPathFactory, ca: dict[str, Any]) -> Any:
    """The loopback server trusting the plant's root CA, with both CAs' revocation lists."""
    base = tmp_path_factory.mktemp("chain")
    app = await start_app(fast_config(base / "data"))
    paths = PkiPaths.in_data_dir(app.data_dir)
    install(paths, trusted=[ca["root"].der], crl=[ca["root"].crl(), ca["issuing"].crl()])
    try:
        yield app
    finally:
        await app.stop()


async def connect(
    app: UacellServer, tmp_path: Path, cert: x509.Certificate, key: Any, uri: str, *, send: bytes | None = None
) -> Client:
    """An asyncua client over Basic256Sha256 SignAndEncrypt; ``send``: the ClientCertificate its
    CreateSession carries instead of its certificate alone (a chain)."""
    client = await secure_client(app.endpoint, tmp_path, cert, key, uri)
    if send is not None:
        create = client.uaclient.create_session

        async def create_with_chain(params: ua.CreateSessionParameters) -> Any:
            params.ClientCertificate = send
            return await create(params)

        client.uaclient.create_session = create_with_chain
    await client.connect()
    return client


@ON_SERVER_LOOP
async def test_a_client_sends_its_chain_and_is_trusted_through_the_root(
    server: UacellServer, tmp_path: Path, ca: dict[str, Any]
) -> None:
    leaf, key, issuing = ca["leaf"], ca["key"], ca["issuing"]
    paths = PkiPaths.in_data_dir(server.data_dir)
    # its certificate alone: the issuing CA is nowhere, so the chain is incomplete
    with pytest.raises(ua.UaStatusCodeError) as err:
        await connect(server, tmp_path, leaf, key, MES)
    assert err.value.code == S.BadSecurityChecksFailed
    # with its chain (OPC 10000-6 6.2.6): the issuing CA comes from the client, the root is trusted
    client = await connect(server, tmp_path, leaf, key, MES, send=der(leaf) + issuing.der)
    try:
        assert await client.nodes.server_state.read_value() == ua.ServerState.Running
    finally:
        await client.disconnect()
    # the issuing CA in pki/issuers/: its certificate alone is enough now
    (paths.issuers / "issuing.der").write_bytes(issuing.der)
    try:
        client = await connect(server, tmp_path, leaf, key, MES)
        assert await client.nodes.server_state.read_value() == ua.ServerState.Running
        await client.disconnect()
    finally:
        (paths.issuers / "issuing.der").unlink()
    assert [p.read_bytes() for p in paths.rejected.iterdir()] == [der(leaf)]  # from the first, incomplete try


@ON_SERVER_LOOP
async def test_a_channel_is_checked_again_with_the_chain_its_session_sent(
    server: UacellServer, tmp_path: Path, ca: dict[str, Any]
) -> None:
    """Decision 100: a client that sends its chain at CreateSession and its certificate alone with the
    channel (as node-opcua does) keeps its channel when the trust list is checked again, since the
    issuer it sent still completes its chain; once the root that made it trusted is gone, it is closed."""
    leaf, key, issuing, root = ca["leaf"], ca["key"], ca["issuing"], ca["root"]
    paths = PkiPaths.in_data_dir(server.data_dir)
    client = await connect(server, tmp_path, leaf, key, MES, send=der(leaf) + issuing.der)
    root_file = next(p for p in paths.trusted.iterdir() if p.read_bytes() == root.der)
    try:
        assert server.security.recheck_channels() == []
        assert await client.nodes.server_state.read_value() == ua.ServerState.Running
        root_file.unlink()
        assert len(server.security.recheck_channels()) == 1
        with pytest.raises((ua.UaError, ConnectionError, TimeoutError)):
            await client.nodes.server_state.read_value()
    finally:
        root_file.write_bytes(root.der)
        with contextlib.suppress(Exception):
            await client.disconnect()


@ON_SERVER_LOOP
async def test_a_client_whose_key_is_too_short_for_the_policy_is_told_so(
    server: UacellServer, tmp_path: Path, ca: dict[str, Any], caplog: pytest.LogCaptureFixture
) -> None:
    """OPC 10000-7 Basic256Sha256 asks for application keys of 2048 to 4096 bits: a client whose
    certificate, issued by the trusted plant CA, has a 1024-bit key gets a channel (asyncua's client can
    make one) but no session, and is told Bad_CertificatePolicyCheckFailed; nothing goes to rejected/,
    since trusting it would not help."""
    caplog.set_level(logging.INFO, logger="uacell.security.policy")  # refusals are logged there, rate-limited
    issuing = ca["issuing"]
    paths = PkiPaths.in_data_dir(server.data_dir)
    rejected_before = sorted(p.name for p in paths.rejected.iterdir())
    small_key = rsa.generate_private_key(public_exponent=65537, key_size=1024)
    small, _ = issuing.application("urn:plant:line3:old-hmi", "Old HMI", key=small_key)
    with pytest.raises(ua.UaStatusCodeError) as err:
        await connect(server, tmp_path, small, small_key, "urn:plant:line3:old-hmi", send=der(small) + issuing.der)
    assert err.value.code == S.BadCertificatePolicyCheckFailed
    assert "1024" in caplog.text and "BadCertificatePolicyCheckFailed" in caplog.text
    assert sorted(p.name for p in paths.rejected.iterdir()) == rejected_before
    client = await connect(server, tmp_path, ca["leaf"], ca["key"], MES, send=der(ca["leaf"]) + issuing.der)
    await client.disconnect()  # the server answers the next client as before


@ON_SERVER_LOOP
async def test_a_revoked_client_is_refused_and_the_log_says_why(
    server: UacellServer, tmp_path: Path, ca: dict[str, Any], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="uacell.security.policy")
    revoked, key, issuing = ca["revoked"], ca["revoked_key"], ca["issuing"]
    with pytest.raises(ua.UaStatusCodeError) as err:
        await connect(server, tmp_path, revoked, key, "urn:plant:line3:old-mes", send=der(revoked) + issuing.der)
    assert err.value.code == S.BadSecurityChecksFailed
    assert "BadCertificateRevoked" in caplog.text
    # the session was not kept: the server still answers others
    client = await connect(server, tmp_path, ca["leaf"], ca["key"], MES, send=der(ca["leaf"]) + issuing.der)
    await client.disconnect()


@ON_SERVER_LOOP
async def test_a_client_certificate_that_is_no_chain_is_invalid(
    server: UacellServer, tmp_path: Path, ca: dict[str, Any]
) -> None:
    leaf = ca["leaf"]
    with pytest.raises(ua.UaStatusCodeError) as err:
        await connect(server, tmp_path, leaf, ca["key"], MES, send=der(leaf) + b"\x30\x82\x01")
    assert err.value.code == S.BadCertificateInvalid


@ON_SERVER_LOOP
async def test_a_session_must_name_the_certificate_of_its_channel(
    server: UacellServer, tmp_path: Path, ca: dict[str, Any]
) -> None:
    """OPC 10000-4 5.7.2.2 (1.05): the ClientCertificate of CreateSession is the one the secure channel
    was opened with. A client holding only a trusted client's certificate (public: it travels in clear
    in OpenSecureChannel) and the key of another must get no session by naming the trusted one."""
    rogue = Authority.root("Rogue CA", key_index=8)
    cert, key = rogue.application(MES, "Rogue", key_index=9)
    trusted = der(ca["leaf"]) + ca["issuing"].der  # a chain uacell trusts
    with pytest.raises(ua.UaStatusCodeError) as err:
        await connect(server, tmp_path, cert, key, MES, send=trusted)
    assert err.value.code == S.BadSecurityChecksFailed


def test_pinning_covers_an_unknown_issuer_of_the_certificate_itself_only(ca: dict[str, Any]) -> None:
    """Its issuer known but the issuer's own issuer not: the chain cannot be built, pinned or not."""
    leaf, issuing = ca["leaf"], ca["issuing"]
    refusal = check_chain([leaf], Anchors(trusted=(leaf,), issuers=(issuing.cert,)), now())
    assert refusal is not None and refusal.code == S.BadCertificateChainIncomplete
    assert refusal.certificate == issuing.cert
