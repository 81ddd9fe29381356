"""node-opcua against `uacell serve` whose certificate the plant's issuing CA issued (decision 95): the
server sends that CA's certificate after its own; node-opcua, trusting the issuing CA (it trusts a
certificate through its direct issuer), accepts the chain and signs ActivateSession and its user
certificate token over the whole chain, which uacell accepts; a client that trusts no CA refuses the
server."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import run_node, start_serve
from helpers import add_user
from plant_ca import Authority, key_pem, pem
from user_certificates import user_certificate

from uacell.config import default_application_uri
from uacell.security.own_certificate import install_certificate, signing_request
from uacell.security.pki import PkiPaths, ensure_server_certificate

pytestmark = pytest.mark.interop

MES = "urn:plant:line3:mes"


def test_node_opcua_trusting_the_plant_ca_reaches_a_server_with_a_certificate_of_the_plant(tmp_path: Path) -> None:
    root = Authority.root()
    issuing = root.intermediate()
    data = tmp_path / "data"
    paths = PkiPaths.in_data_dir(data)
    uri, hosts = default_application_uri(), ["127.0.0.1"]  # what `uacell serve --host 127.0.0.1` uses
    ensure_server_certificate(paths, uri, hosts)
    issued = issuing.sign_request(signing_request(paths, uri, hosts))
    install_certificate(paths, pem(issued) + pem(issuing.cert), uri, hosts)
    (paths.trusted / "root.der").write_bytes(root.der)
    (paths.issuers / "issuing.der").write_bytes(issuing.der)
    for name, crl in (("root.crl", root.crl()), ("issuing.crl", issuing.crl())):
        (paths.crl / name).write_bytes(crl)
        (tmp_path / name).write_bytes(crl)
    mes, mes_key = issuing.application(MES)
    (tmp_path / "mes.pem").write_bytes(pem(mes))
    (tmp_path / "mes-key.pem").write_bytes(key_pem(mes_key))
    (tmp_path / "issuing.pem").write_bytes(pem(issuing.cert))
    olga = user_certificate("olga")
    olga_cert, olga_key = olga.write(tmp_path, "olga")
    add_user(data, "olga", "--role", "engineer", "--certificate", str(olga_cert))
    sp = start_serve(data, log_level="INFO")
    try:
        out = run_node(
            "server_chain.js",
            sp.endpoint,
            str(tmp_path / "pki-plant"),
            str(tmp_path / "pki-nobody"),
            str(tmp_path / "issuing.pem"),
            str(tmp_path / "mes.pem"),
            str(tmp_path / "mes-key.pem"),
            MES,
            str(olga_cert),
            str(olga_key),
            str(tmp_path / "root.crl"),
            str(tmp_path / "issuing.crl"),
        )
    finally:
        sp.stop()
    assert out["plant"] == {"state": 0, "role": "engineer"}, out
    assert "BadCertificateUntrusted" in out["nobody"]["error"], out
    assert "the server certificate is sent with 1 certificate(s) of its CA" in "".join(sp.output)
