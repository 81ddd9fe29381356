"""node-opcua as a GDS (interop/trust_list.js) reading and writing the trust list of `uacell serve` as a
file (OPC 10000-12 7.8.2, decision 97), with node-opcua's own TrustListDataType encoding and decoding it."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
from conftest import run_node, start_serve
from helpers import add_user
from plant_ca import Authority, key_pem, pem

from uacell.security.pki import PkiPaths

pytestmark = pytest.mark.interop

PASSWORD = "trust-list-pw-1"
GDS = "urn:plant:gds"


def sha1(data: bytes) -> str:
    return hashlib.sha1(data).hexdigest()


def test_node_opcua_reads_and_replaces_the_trust_list_as_a_file(tmp_path: Path) -> None:
    root = Authority.root()
    issuing = root.intermediate()
    contractor = Authority.root("Contractor CA", key_index=4)
    gds_cert, gds_key = issuing.application(GDS, "Plant GDS")
    data = tmp_path / "data"
    paths = PkiPaths.in_data_dir(data)
    paths.create()
    root_crl, issuing_crl, contractor_crl = root.crl(), issuing.crl(), contractor.crl()
    (paths.trusted / "root.der").write_bytes(root.der)
    (paths.issuers / "issuing.der").write_bytes(issuing.der)
    (paths.crl / "root.crl").write_bytes(root_crl)
    (paths.crl / "issuing.crl").write_bytes(issuing_crl)
    for name, content in {
        "gds.pem": pem(gds_cert),
        "gds-key.pem": key_pem(gds_key),
        "contractor.pem": pem(contractor.cert),
        "root.crl": root_crl,
        "contractor.crl": contractor_crl,
    }.items():
        (tmp_path / name).write_bytes(content)
    add_user(data, "ada", "--role", "admin", password=PASSWORD)
    gds = [str(tmp_path / "pki-gds"), str(tmp_path / "gds.pem"), str(tmp_path / "gds-key.pem"), GDS, "ada", PASSWORD]
    sp = start_serve(data)
    try:
        read = run_node("trust_list.js", sp.endpoint, *gds, "read")
        written = run_node(
            "trust_list.js",
            sp.endpoint,
            *gds,
            "write",
            str(tmp_path / "contractor.pem"),
            str(tmp_path / "root.crl"),
            str(tmp_path / "contractor.crl"),
        )
    finally:
        sp.stop()
    assert read == {
        "specifiedLists": 15,
        "trusted": [sha1(root.der)],
        "trustedCrls": [sha1(root_crl)],  # signed by a trusted certificate
        "issuers": [sha1(issuing.der)],
        "issuerCrls": [sha1(issuing_crl)],
        "openCount": 1,  # its own handle, while it reads
    }, read
    # node-opcua writes the lists it does not specify as empty arrays (not null): they are left as they are
    assert sorted(written.pop("after")) == sorted([sha1(root.der), sha1(contractor.der)]), written
    assert written == {"status": "Good", "applyChangesRequired": False}, written
    assert sorted(p.name for p in paths.trusted.iterdir()) == sorted(
        f"{sha1(c)}.der" for c in (root.der, contractor.der)
    )
    assert sorted(p.read_bytes() for p in paths.crl.iterdir()) == sorted([root_crl, issuing_crl, contractor_crl])
    assert (paths.issuers / "issuing.der").read_bytes() == issuing.der
