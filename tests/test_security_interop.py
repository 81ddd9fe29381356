"""node-opcua against `uacell serve`: Basic256Sha256 SignAndEncrypt with a user name made by `uacell user add`."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from conftest import run_node, start_serve
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from user_certificates import user_certificate

from uacell.security.pki import PkiPaths, TrustList, make_client_certificate
from uacell.security.users import thumbprint

pytestmark = pytest.mark.interop

NODE_URI = "urn:uacell:test:node-opcua"


def node_client(tmp_path: Path, data: Path) -> list[str]:
    """An application certificate for the node-opcua client, trusted by the server of ``data``: the
    arguments the scripts take for it (certificate, key, application URI, node-opcua's PKI folder)."""
    der, key_pem = make_client_certificate(NODE_URI)
    cert_file, key_file = tmp_path / "node-cert.pem", tmp_path / "node-key.pem"
    cert_file.write_bytes(x509.load_der_x509_certificate(der).public_bytes(serialization.Encoding.PEM))
    key_file.write_bytes(key_pem)
    TrustList(PkiPaths.in_data_dir(data)).trust(der)
    return [str(cert_file), str(key_file), NODE_URI, str(tmp_path / "node-pki")]


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
    client = node_client(tmp_path, data)
    # Loosening (here: tightening) a default is logged at start-up.
    config = tmp_path / "uacell.toml"
    config.write_text("[server]\nallow_none_security = false\n")
    sp = start_serve(data, "--config", str(config))
    try:
        out = run_node(
            "secure.js",
            sp.endpoint,
            *client,
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


def test_node_opcua_logs_in_with_user_certificates_bound_by_the_command_line(tmp_path):
    """Users bound to certificates with `uacell user add --certificate` and `uacell user certificate`;
    node-opcua signs the token with the None endpoint's certificate policy (decision 84)."""
    data = tmp_path / "data"
    olga, stranger = user_certificate("olga"), user_certificate("stranger")
    olga_cert, olga_key = olga.write(tmp_path, "olga")
    _, stranger_key = stranger.write(tmp_path, "stranger")
    olga_der = tmp_path / "olga.der"  # node-opcua sends certificateData as it reads it: DER
    olga_der.write_bytes(olga.der)
    stranger_der = tmp_path / "stranger.der"
    stranger_der.write_bytes(stranger.der)

    def uacell_user(*args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "uacell", "user", "--data-dir", str(data), *args],
            input=stdin,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )

    added = uacell_user("add", "olga", "--role", "engineer", "--certificate", str(olga_cert))
    assert added.returncode == 0, added.stderr
    assert f"logging in with certificate {thumbprint(olga.der)}" in added.stdout
    assert uacell_user("add", "ann", "--role", "admin", "--password-stdin", stdin="admin password 1\n").returncode == 0
    twice = uacell_user("certificate", "ann", str(olga_cert))
    assert twice.returncode == 1 and "bound to user 'olga' already" in twice.stderr
    listed = uacell_user("list").stdout.splitlines()
    assert listed[1:] == ["ann\tadmin", f"olga\tengineer\tcertificate {thumbprint(olga.der)}"]
    sp = start_serve(data)
    try:
        out = run_node(
            "x509_login.js",
            sp.endpoint,
            *("olga", str(olga_der), str(olga_key)),
            *("stranger", str(stranger_der), str(stranger_key)),
            *("wrong-key", str(olga_der), str(stranger_key)),
        )
    finally:
        sp.stop()
    assert out["olga"] == {"role": "engineer"}
    assert "BadIdentityTokenRejected" in out["stranger"]["error"]
    assert "BadUserSignatureInvalid" in out["wrong-key"]["error"]
    assert out["changeUser"]["status"] == "Good"
    # an anonymous session on loopback is an operator, then the certificate's user
    assert (out["changeUser"]["before"], out["changeUser"]["after"]) == ("operator", "engineer")
    removed = uacell_user("certificate", "olga", "--remove", thumbprint(olga.der))
    assert removed.returncode == 1 and "only way user 'olga' logs in" in removed.stderr
