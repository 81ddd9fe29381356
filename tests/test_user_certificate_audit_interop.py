"""node-opcua reads the AuditCertificate events `uacell serve` fires for refused X.509 user certificates
(decision 102): an expired certificate bound to a user is AuditCertificateExpiredEventType with
Bad_CertificateTimeInvalid, one bound to nobody AuditCertificateUntrustedEventType with
Bad_CertificateUntrusted; each login is told Bad_IdentityTokenRejected. The certificates are made from RFC
5280 in tests/user_certificates.py."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest
from asyncua import ua
from conftest import run_node, start_serve
from user_certificates import user_certificate

from uacell.core.roles import Role
from uacell.security.users import UserStore

pytestmark = pytest.mark.interop

PASSWORD = "user-cert-audit-pw-1"


def test_node_opcua_reads_the_certificate_events_of_refused_user_certificates(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    expired = user_certificate("old badge", not_before=dt.datetime.now(dt.UTC) - dt.timedelta(days=40), days=30)
    stranger = user_certificate("somebody")
    users = UserStore(data / "users.toml")
    users.add("ada", Role.ADMIN, PASSWORD)
    users.add("oldie", Role.OPERATOR, None, certificate=expired.der)
    args = []
    for label, cert in (("expired", expired), ("stranger", stranger)):
        _, key = cert.write(tmp_path, label)
        (tmp_path / f"{label}.der").write_bytes(cert.der)  # node-opcua sends certificateData as it reads it
        args += [label, str(tmp_path / f"{label}.der"), str(key)]
    sp = start_serve(data)
    try:
        out = run_node("user_certificate_audit.js", sp.endpoint, "ada", PASSWORD, *args)
    finally:
        sp.stop()
    assert all("BadIdentityTokenRejected" in (out["refused"][label] or "") for label in ("expired", "stranger")), out
    by_certificate = {bytes.fromhex(e["certificate"]): e for e in out["events"]}
    assert by_certificate[expired.der]["type"] == f"ns=0;i={ua.ObjectIds.AuditCertificateExpiredEventType}"
    assert by_certificate[expired.der]["status"] == "BadCertificateTimeInvalid"
    assert by_certificate[stranger.der]["type"] == f"ns=0;i={ua.ObjectIds.AuditCertificateUntrustedEventType}"
    assert by_certificate[stranger.der]["status"] == "BadCertificateUntrusted"
    assert len(out["events"]) == 2, out["events"]
