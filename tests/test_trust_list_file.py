"""The trust list as a file (OPC 10000-12 7.8.2, decision 97), pure: the TrustListDataType as OPC 10000-6 5.2
encodes it (written out here from the standard's rules, not from uacell's code), what a handle reads and
writes, CloseAndUpdate's replacement and its refusals (each leaves every file as it was), the activity
timeout on an injected clock and a replacement a crash cut short."""

from __future__ import annotations

import datetime as dt
import hashlib
import os
import time
from pathlib import Path
from typing import Any

import pytest
from cryptography.hazmat.primitives.asymmetric import rsa
from plant_ca import Authority, der, signed_with_sha1, trust_list_bytes

from uacell.core.errors import CallError
from uacell.core.file_paths import MODE_READ
from uacell.security.pki import PkiPaths
from uacell.security.trust_list_file import (
    ALL,
    ISSUER_CRLS,
    ISSUERS,
    MODE_WRITE_ERASE,
    TRUSTED,
    TRUSTED_CRLS,
    TrustListContent,
    TrustListFile,
    check_content,
    finish_update,
    last_update,
    read_content,
    write_content,
)


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


@pytest.fixture
def pki(tmp_path: Path) -> dict[str, Any]:
    """A plant: its root trusted, the issuing CA an issuer, both CRLs; a contractor's CA outside."""
    root = Authority.root()
    issuing = root.intermediate()
    paths = PkiPaths(tmp_path / "pki")
    paths.create()
    (paths.trusted / "root.der").write_bytes(root.der)
    (paths.issuers / "issuing.der").write_bytes(issuing.der)
    root_crl, issuing_crl = root.crl(), issuing.crl()
    (paths.crl / "root.crl").write_bytes(root_crl)
    (paths.crl / "issuing.crl").write_bytes(issuing_crl)
    return {"paths": paths, "root": root, "issuing": issuing, "root_crl": root_crl, "issuing_crl": issuing_crl}


def files(paths: PkiPaths) -> dict[str, bytes]:
    return {
        str(f.relative_to(paths.root)): f.read_bytes()
        for folder in (paths.trusted, paths.issuers, paths.crl, paths.rejected)
        for f in sorted(folder.iterdir())
    }


def read_all(trust: TrustListFile, session: str, handle: int, chunk: int = 100) -> bytes:
    data = b""
    while part := trust.read(session, handle, chunk):
        data += part
    return data


def test_the_file_is_the_standards_encoding_of_the_lists(pki: dict[str, Any]) -> None:
    paths, root, issuing = pki["paths"], pki["root"], pki["issuing"]
    trust = TrustListFile(paths)
    handle = trust.open("gds", MODE_READ)
    assert trust.open_count == 1
    # a trusted CRL is one a trusted certificate signed; the others are issuer CRLs
    expected = trust_list_bytes(ALL, [root.der], [pki["root_crl"]], [issuing.der], [pki["issuing_crl"]])
    assert read_all(trust, "gds", handle, chunk=37) == expected
    assert trust.get_position("gds", handle) == len(expected)
    trust.set_position("gds", handle, 10**9)  # past the end: the end
    assert trust.get_position("gds", handle) == len(expected) and trust.read("gds", handle, 10) == b""
    trust.set_position("gds", handle, 0)
    assert trust.read("gds", handle, len(expected) + 10) == expected
    trust.close("gds", handle)
    assert trust.open_count == 0
    # only what the masks name, the other arrays null
    masked = trust.open_with_masks("gds", ISSUERS | TRUSTED_CRLS)
    expected = trust_list_bytes(ISSUERS | TRUSTED_CRLS, None, [pki["root_crl"]], [issuing.der], None)
    assert read_all(trust, "gds", masked) == expected
    assert TrustListContent.decode(expected) == TrustListContent(
        (), (pki["root_crl"],), (issuing.der,), (), ISSUERS | TRUSTED_CRLS
    )


def test_a_reader_reads_the_list_as_it_was_when_opened(pki: dict[str, Any]) -> None:
    paths = pki["paths"]
    trust = TrustListFile(paths)
    handle = trust.open("gds", MODE_READ)
    first = trust.read("gds", handle, 50)
    (paths.trusted / "root.der").unlink()  # changed out of band, by `uacell cert remove`
    rest = read_all(trust, "gds", handle)
    assert TrustListContent.decode(first + rest).trusted == (pki["root"].der,)


def test_a_gds_replaces_the_trusted_certificates_and_their_crls(pki: dict[str, Any]) -> None:
    paths, root, issuing = pki["paths"], pki["root"], pki["issuing"]
    contractor = Authority.root("Contractor CA", key_index=4)
    mes, _ = issuing.application("urn:plant:line3:mes", "MES", key_index=3)
    (paths.rejected / f"{thumb(der(mes))}.der").write_bytes(der(mes))
    (paths.trusted / "notes.txt").write_text("kept: not a certificate")
    before = files(paths)
    trust = TrustListFile(paths)
    handle = trust.open("gds", MODE_WRITE_ERASE)
    contractor_crl = contractor.crl()
    content = trust_list_bytes(TRUSTED | TRUSTED_CRLS, [contractor.der, der(mes)], [contractor_crl])
    for i in range(0, len(content), 500):  # in pieces, as a client writes a large file
        trust.write("gds", handle, content[i : i + 500])
    checked = trust.close_and_update("gds", handle, now())
    assert trust.open_count == 0 and not paths.trust_update.exists()
    assert sorted(p.name for p in paths.trusted.iterdir()) == sorted(
        [f"{thumb(contractor.der)}.der", f"{thumb(der(mes))}.der", "notes.txt"]
    )
    assert (paths.trusted / f"{thumb(der(mes))}.der").read_bytes() == der(mes)
    assert not (paths.rejected / f"{thumb(der(mes))}.der").exists()  # trusted now
    # the issuers are not specified: kept; the CRL folder holds the new trusted CRL and the issuer CRL kept
    assert files(paths)["issuers/issuing.der"] == before["issuers/issuing.der"]
    after = read_content(paths)
    assert after.issuers == (issuing.der,)
    assert after.trusted_crls == (contractor_crl,)  # the root's CRL was a trusted CRL: replaced
    assert after.issuer_crls == (pki["issuing_crl"],)
    assert len(checked.trusted) == 2 and checked.warnings == ()
    assert root.der not in after.trusted


def test_what_close_and_update_refuses_leaves_every_file_and_closes_the_handle(pki: dict[str, Any]) -> None:
    paths, root = pki["paths"], pki["root"]
    stranger = Authority.root("Stranger CA", key_index=5)
    not_a_ca = root.intermediate("Not a CA", key_index=7, ca=False)
    before = files(paths)
    cases = [
        (b"\x01\x00", "BadDecodingError"),  # ends inside SpecifiedLists
        (trust_list_bytes(TRUSTED, [root.der]) + b"\x00", "BadDecodingError"),  # bytes after it
        (trust_list_bytes(16, [root.der]), "BadInvalidArgument"),  # SpecifiedLists outside TrustListMasks
        (trust_list_bytes(TRUSTED, [b"junk"]), "BadCertificateInvalid"),
        (trust_list_bytes(ISSUERS, None, None, [not_a_ca.der]), "BadCertificateIssuerUseNotAllowed"),
        (trust_list_bytes(TRUSTED_CRLS, None, [b"junk"]), "BadCertificateInvalid"),
        (trust_list_bytes(ISSUER_CRLS, None, None, None, [stranger.crl()]), "BadCertificateChainIncomplete"),
        # the root dropped from the trusted certificates, its CRL kept (not specified): the whole list is checked
        (trust_list_bytes(TRUSTED, [stranger.der]), "BadCertificateChainIncomplete"),
    ]
    # a certificate named as issued by a CA of the list but not signed by it
    impostor = Authority.root("Plant Issuing CA", key_index=8)  # the issuing CA's name, another key
    forged = impostor.application("urn:forged", "Forged", key_index=6)[0]
    cases.append((trust_list_bytes(TRUSTED, [root.der, der(forged)]), "BadCertificateInvalid"))
    # a client certificate no security policy uacell offers would accept (decision 101): 1024-bit key, SHA-1
    small = root.application("urn:old", "Old", key=rsa.generate_private_key(public_exponent=65537, key_size=1024))[0]
    cases.append((trust_list_bytes(TRUSTED, [root.der, der(small)]), "BadCertificatePolicyCheckFailed"))
    sha1 = signed_with_sha1(root.application("urn:sha1", "SHA-1 client", key_index=6)[0], root.key)
    cases.append((trust_list_bytes(TRUSTED, [root.der, der(sha1)]), "BadCertificatePolicyCheckFailed"))
    trust = TrustListFile(paths)
    for content, code in cases:
        handle = trust.open("gds", MODE_WRITE_ERASE)
        trust.write("gds", handle, content)
        with pytest.raises(CallError) as refused:
            trust.close_and_update("gds", handle, now())
        assert refused.value.status == code, content
        assert trust.open_count == 0  # closed, whatever the outcome
        assert files(paths) == before and not paths.trust_update.exists()


def test_a_certificate_out_of_its_validity_is_kept_with_a_warning(pki: dict[str, Any]) -> None:
    paths, root = pki["paths"], pki["root"]
    old = root.intermediate("Old CA", key_index=9, not_before=now() - dt.timedelta(days=30), days=10)
    checked = check_content(TrustListContent(trusted=(root.der, old.der)), now())
    assert [c.subject for c in checked.trusted] == [root.cert.subject, old.cert.subject]
    assert len(checked.warnings) == 1 and "Old CA" in checked.warnings[0]
    write_content(paths, checked, TRUSTED)
    assert set(read_content(paths).trusted) == {root.der, old.der}


def test_handles_modes_and_sessions(pki: dict[str, Any]) -> None:
    paths = pki["paths"]
    trust = TrustListFile(paths, max_size=100)
    for mode in (0, 2, 3, 4, 5, 7):
        with pytest.raises(CallError) as refused:
            trust.open("gds", mode)
        assert refused.value.status == "BadNotSupported"
    with pytest.raises(CallError) as refused:
        trust.open_with_masks("gds", 16)
    assert refused.value.status == "BadInvalidArgument"
    reader = trust.open("hmi", MODE_READ)
    with pytest.raises(CallError) as refused:
        trust.open("gds", MODE_WRITE_ERASE)  # a reader is open
    assert refused.value.status == "BadNotWritable"
    with pytest.raises(CallError) as refused:
        trust.refuse_changes()  # AddCertificate, RemoveCertificate
    assert refused.value.status == "BadInvalidState"
    with pytest.raises(CallError) as refused:
        trust.read("gds", reader, 10)  # another session's handle
    assert refused.value.status == "BadInvalidArgument"
    with pytest.raises(CallError) as refused:
        trust.write("hmi", reader, b"x")
    assert refused.value.status == "BadInvalidState"
    assert trust.close_session("hmi") == 1 and trust.open_count == 0
    writer = trust.open("gds", MODE_WRITE_ERASE)
    with pytest.raises(CallError) as refused:
        trust.open("gds", MODE_WRITE_ERASE)
    assert refused.value.status == "BadNotWritable"
    with pytest.raises(CallError) as refused:
        trust.open("hmi", MODE_READ)
    assert refused.value.status == "BadNotReadable"
    with pytest.raises(CallError) as refused:
        trust.read("gds", writer, 10)
    assert refused.value.status == "BadInvalidState"
    trust.write("gds", writer, b"a" * 100)
    with pytest.raises(CallError) as refused:
        trust.write("gds", writer, b"b")  # beyond MaxTrustListSize
    assert refused.value.status == "BadResourceUnavailable"
    before = files(paths)
    trust.close("gds", writer)  # Close drops what was written
    assert files(paths) == before and trust.open_count == 0
    with pytest.raises(CallError) as refused:
        trust.close("gds", writer)
    assert refused.value.status == "BadInvalidArgument"


def test_handles_close_when_the_trust_list_sees_no_call_for_its_activity_timeout(pki: dict[str, Any]) -> None:
    clock = Clock()
    trust = TrustListFile(pki["paths"], activity_timeout=60.0, clock=clock)
    trust.touch()
    writer = trust.open("gds", MODE_WRITE_ERASE)
    clock.t += 59.0
    assert trust.touch() == 0 and trust.expire() == 0
    trust.write("gds", writer, b"x")
    clock.t += 60.5
    assert trust.expire() == 1 and trust.open_count == 0
    with pytest.raises(CallError) as refused:
        trust.write("gds", writer, b"y")
    assert refused.value.status == "BadInvalidArgument"
    assert trust.open("other", MODE_WRITE_ERASE) > 0  # the list is free again


def test_a_replacement_a_crash_cut_short_is_finished_or_dropped(pki: dict[str, Any]) -> None:
    paths, root = pki["paths"], pki["root"]
    contractor = Authority.root("Contractor CA", key_index=4)
    checked = check_content(TrustListContent(trusted=(contractor.der,)), now())
    # the crash came after the marker, while the files were copied: the start finishes the job
    staged = paths.trust_update / "trusted"
    staged.mkdir(parents=True)
    (staged / f"{thumb(contractor.der)}.der").write_bytes(contractor.der)
    (paths.trust_update / "replace").write_text("trusted\n")
    (paths.trusted / f"{thumb(contractor.der)}.der").write_bytes(contractor.der[:10])  # half a copy
    assert finish_update(paths)
    assert read_content(paths).trusted == (contractor.der,) and not paths.trust_update.exists()
    # the crash came before the marker: the old lists stay
    before = files(paths)
    staged.mkdir(parents=True)
    (staged / f"{thumb(root.der)}.der").write_bytes(root.der)
    assert not finish_update(paths)
    assert files(paths) == before and not paths.trust_update.exists()
    assert not finish_update(paths)  # nothing to do
    assert checked.trusted == (contractor.cert,)


def test_last_update_follows_the_folders(pki: dict[str, Any]) -> None:
    paths = pki["paths"]
    first = last_update(paths)
    contractor = Authority.root("Contractor CA", key_index=4)
    later = time.time() + 5
    write_content(paths, check_content(TrustListContent(trusted=(contractor.der,)), now()), TRUSTED)
    os.utime(paths.trusted, (later, later))
    assert last_update(paths) > first
    assert last_update(paths) == dt.datetime.fromtimestamp(later, dt.UTC)


def thumb(data: bytes) -> str:
    return hashlib.sha1(data).hexdigest()
