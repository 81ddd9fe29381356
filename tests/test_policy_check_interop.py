"""node-opcua with a certificate whose RSA key is too short for Basic256Sha256 (OPC 10000-7: 2048 to 4096
bits), trusted by `uacell serve`, is told Bad_CertificatePolicyCheckFailed at CreateSession (decision 101);
the same client with a 2048-bit certificate gets its session. The certificates are made here from RFC
5280 (tests/plant_ca.py), not by uacell."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from conftest import run_node, start_serve
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from plant_ca import application_certificate, der

from uacell.security.pki import PkiPaths, TrustList

pytestmark = [pytest.mark.interop, pytest.mark.asyncio]
URI = "urn:plant:node-hmi"


def client_files(tmp_path: Path, data: Path, bits: int) -> list[str]:
    """A self-signed client certificate of ``bits`` for node-opcua, trusted by the server of ``data``."""
    key = rsa.generate_private_key(public_exponent=65537, key_size=bits)
    cert = application_certificate(URI, f"node-opcua {bits}", key)
    cert_file, key_file = tmp_path / f"cert-{bits}.pem", tmp_path / f"key-{bits}.pem"
    cert_file.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_file.write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    TrustList(PkiPaths.in_data_dir(data)).trust(der(cert))
    return [str(cert_file), str(key_file), URI, str(tmp_path / f"node-pki-{bits}")]


async def test_node_opcua_with_a_1024_bit_key_is_told_the_policy_check_failed(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    weak, strong = client_files(tmp_path, data, 1024), client_files(tmp_path, data, 2048)
    sp = start_serve(data)
    try:
        refused = await asyncio.to_thread(run_node, "policy_check.js", sp.endpoint, *weak)
        admitted = await asyncio.to_thread(run_node, "policy_check.js", sp.endpoint, *strong)
    finally:
        sp.stop()
    assert refused == {"session": False, "status": "BadCertificatePolicyCheckFailed"}, refused
    assert admitted == {"session": True, "status": ""}, admitted
