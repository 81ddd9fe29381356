"""node-opcua with certificates a plant's CA issued, against `uacell serve` trusting that CA's root
(decision 92): node-opcua sends its chain in OpenSecureChannel and its certificate alone in
CreateSession; a revoked certificate, one without its chain and one of another CA (with its chain)
are refused."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import run_node, start_serve
from cryptography import x509
from plant_ca import Authority, der, key_pem, pem

from uacell.security.pki import PkiPaths

pytestmark = pytest.mark.interop

MES = "urn:plant:line3:mes"


def client_files(directory: Path, label: str, chain: list[x509.Certificate], key_bytes: bytes) -> list[str]:
    cert, key = directory / f"{label}-cert.pem", directory / f"{label}-key.pem"
    cert.write_bytes(b"".join(pem(c) for c in chain))
    key.write_bytes(key_bytes)
    return [str(cert), str(key)]


def test_node_opcua_clients_of_a_plant_ca(tmp_path: Path) -> None:
    root = Authority.root()
    issuing = root.intermediate()
    mes, mes_key = issuing.application(MES)
    old, old_key = issuing.application("urn:plant:line3:old-mes", "Old MES", key_index=3)
    issuing.revoke(old)
    other = Authority.root("Contractor CA", key_index=4)
    stranger, stranger_key = other.application("urn:contractor:laptop", "Laptop", key_index=5)

    data = tmp_path / "data"
    paths = PkiPaths.in_data_dir(data)
    paths.create()
    (paths.trusted / "plant-root.der").write_bytes(root.der)
    (paths.crl / "plant-root.crl").write_bytes(root.crl())
    (paths.crl / "plant-issuing.crl").write_bytes(issuing.crl())

    args = [
        *("mes", *client_files(tmp_path, "mes", [mes, issuing.cert], key_pem(mes_key)), MES),
        *("alone", *client_files(tmp_path, "alone", [mes], key_pem(mes_key)), MES),
        *(
            "revoked",
            *client_files(tmp_path, "revoked", [old, issuing.cert], key_pem(old_key)),
            "urn:plant:line3:old-mes",
        ),
        *(
            "stranger",
            *client_files(tmp_path, "stranger", [stranger, other.cert], key_pem(stranger_key)),
            "urn:contractor:laptop",
        ),
    ]
    sp = start_serve(data, log_level="INFO")
    try:
        out = run_node("ca_chain.js", sp.endpoint, str(tmp_path / "node-pki"), *args)
    finally:
        sp.stop()
    log = "".join(sp.output)
    assert out["mes"] == {"state": 0}  # ServerState Running, through the chain node-opcua sent
    assert "BadSecurityChecksFailed" in out["alone"]["error"]
    assert "BadSecurityChecksFailed" in out["revoked"]["error"]
    assert "BadCertificateUntrusted" in out["stranger"]["error"]
    assert "BadCertificateChainIncomplete" in log and "BadCertificateRevoked" in log
    # what trusting it by itself would let in waits in rejected/: the chainless MES and the contractor's
    # (a certificate trusted by itself needs no revocation list); the revoked one does not
    assert sorted(p.read_bytes() for p in paths.rejected.iterdir()) == sorted([der(mes), der(stranger)])
