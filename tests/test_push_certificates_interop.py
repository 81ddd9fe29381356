"""node-opcua as a GDS (interop/gds_push.js) pushing the certificate of `uacell serve` through
ServerConfiguration (OPC 10000-12 7.10, decision 96): a request for a new key, the certificate the plant's
CA issued for it, UpdateCertificate and ApplyChanges; then a node-opcua client that trusts only that CA,
without automatic acceptance, reaches the server."""

from __future__ import annotations

import base64
import hashlib
from pathlib import Path

import pytest
from conftest import run_node, start_serve
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from helpers import add_user
from plant_ca import Authority, der, key_pem, pem

from uacell.security.pki import PkiPaths

pytestmark = pytest.mark.interop

PASSWORD = "push-certificates-pw-1"
GDS = "urn:plant:gds"


def test_node_opcua_as_a_gds_pushes_a_certificate_that_a_strict_client_then_trusts(tmp_path: Path) -> None:
    root = Authority.root()
    issuing = root.intermediate()
    gds_cert, gds_key = issuing.application(GDS, "Plant GDS")
    data = tmp_path / "data"
    paths = PkiPaths.in_data_dir(data)
    paths.create()
    (paths.trusted / "root.der").write_bytes(root.der)
    (paths.issuers / "issuing.der").write_bytes(issuing.der)
    for name, crl in (("root.crl", root.crl()), ("issuing.crl", issuing.crl())):
        (paths.crl / name).write_bytes(crl)
        (tmp_path / name).write_bytes(crl)
    mes, _ = issuing.application("urn:plant:line3:mes", "MES", key_index=3)
    files = {
        "gds.pem": pem(gds_cert),
        "gds-key.pem": key_pem(gds_key),
        "issuing.pem": pem(issuing.cert),
        "mes.pem": pem(mes),
    }
    for name, content in files.items():
        (tmp_path / name).write_bytes(content)
    add_user(data, "ada", "--role", "admin", password=PASSWORD)
    sp = start_serve(data, log_level="INFO")
    try:
        gds = [
            str(tmp_path / "pki-gds"),
            str(tmp_path / "gds.pem"),
            str(tmp_path / "gds-key.pem"),
            GDS,
            "ada",
            PASSWORD,
        ]
        asked = run_node("gds_push.js", sp.endpoint, *gds, "request")
        assert asked["status"] == "Good", asked
        request = x509.load_der_x509_csr(base64.b64decode(asked["request"]))
        assert request.subject.rfc4514_string() == "O=Plant,CN=uacell line 3"
        (tmp_path / "issued.pem").write_bytes(
            pem(issuing.sign_request(request.public_bytes(serialization.Encoding.PEM)))
        )
        pushed = run_node(
            "gds_push.js",
            sp.endpoint,
            *gds,
            "update",
            str(tmp_path / "issued.pem"),
            str(tmp_path / "issuing.pem"),
            str(tmp_path / "issuing.pem"),
            str(tmp_path / "mes.pem"),
            str(tmp_path / "root.crl"),
            str(tmp_path / "issuing.crl"),
        )
    finally:
        sp.stop()
    assert pushed["update"] == {"status": "Good", "outputs": [True]}, pushed
    assert pushed["apply"] == {"status": "Good", "outputs": []}, pushed
    assert pushed["rejected"]["status"] == "Good", pushed
    assert (pushed["added"], pushed["removed"]) == ("Good", "Good"), pushed
    assert not list(paths.trusted.glob(f"{hashlib.sha1(der(mes)).hexdigest()}*"))
    # a client that trusts only the plant's issuing CA, without automatic acceptance, reaches the server now
    assert pushed["after"] == {"state": 0}, pushed
    assert paths.cert.read_bytes() == der(x509.load_pem_x509_certificate((tmp_path / "issued.pem").read_bytes()))
