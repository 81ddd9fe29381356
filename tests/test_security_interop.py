"""node-opcua against `uacell serve`: Basic256Sha256 SignAndEncrypt with a user name made by `uacell user add`."""

from __future__ import annotations

import subprocess
import sys

import pytest
from conftest import run_node, start_serve
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from uacell.security.pki import PkiPaths, TrustList, make_client_certificate

pytestmark = pytest.mark.interop

NODE_URI = "urn:uacell:test:node-opcua"


def test_node_opcua_secure_session_with_user_name(tmp_path):
    data = tmp_path / "data"
    # the user comes from the command line, the password from stdin
    add = subprocess.run(
        [
            sys.executable,
            "-m",
            "uacell",
            "user",
            "--data-dir",
            str(data),
            "add",
            "nora",
            "--role",
            "operator",
            "--password-stdin",
        ],
        input="n0de-secret\n",
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert add.returncode == 0, add.stderr
    listed = subprocess.run(
        [sys.executable, "-m", "uacell", "user", "--data-dir", str(data), "list"],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    assert listed.stdout.splitlines() == [f"{data / 'users.toml'}: 1 user", "nora\toperator"]
    der, key_pem = make_client_certificate(NODE_URI)
    cert_file, key_file = tmp_path / "node-cert.pem", tmp_path / "node-key.pem"
    cert_file.write_bytes(x509.load_der_x509_certificate(der).public_bytes(serialization.Encoding.PEM))
    key_file.write_bytes(key_pem)
    TrustList(PkiPaths.in_data_dir(data)).trust(der)
    # Loosening (here: tightening) a default is logged at start-up.
    config = tmp_path / "uacell.toml"
    config.write_text("[server]\nallow_none_security = false\n")
    sp = start_serve(data, "--config", str(config))
    try:
        out = run_node(
            "secure.js",
            sp.endpoint,
            str(cert_file),
            str(key_file),
            NODE_URI,
            str(tmp_path / "node-pki"),
            "nora",
            "n0de-secret",
        )
    finally:
        sp.stop()
    assert out["securityMode"] == "SignAndEncrypt"
    assert out["securityPolicy"].endswith("#Basic256Sha256")
    assert out["initLock"] == {"status": "Good", "value": 0}
    assert out["locked"] is True
    assert out["lockingUser"] == "nora"
    assert out["lockingClient"] == NODE_URI
    assert out["breakLock"]["status"] == "BadUserAccessDenied"  # operators may not break locks
    assert out["userExecutableInit"] is True and out["userExecutableBreak"] is False
    assert out["exitLock"] == {"status": "Good", "value": 0}
    assert out["lockedAfterExit"] is False
    assert "BadUserAccessDenied" in out["wrongPassword"] or "UserAccessDenied" in out["wrongPassword"]
    output = "".join(sp.output)
    assert "SecurityPolicy None is not offered while listening on loopback only" in output
