"""node-opcua connected to `uacell serve` with a trusted certificate while `uacell cert remove` takes it out
of the trust list from another process (decision 100): its channel is closed, and a new one is refused."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import run_node, start_serve
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from helpers import wait_until
from test_security_interop import node_client

pytestmark = [pytest.mark.interop, pytest.mark.asyncio]


async def test_node_opcua_channel_closes_when_its_certificate_is_removed(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    client = node_client(tmp_path, data)
    cert_file, ready = Path(client[0]), tmp_path / "ready"
    der = x509.load_pem_x509_certificate(cert_file.read_bytes()).public_bytes(serialization.Encoding.DER)
    (tmp_path / "node.der").write_bytes(der)
    sp = start_serve(data)
    try:
        outcome = asyncio.create_task(asyncio.to_thread(run_node, "trust_removed.js", sp.endpoint, *client, str(ready)))
        await wait_until(ready.exists, timeout=60, step=0.05)
        removed = await asyncio.to_thread(
            subprocess.run,
            [sys.executable, "-m", "uacell", "cert", "remove", str(tmp_path / "node.der"), "--data-dir", str(data)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert removed.returncode == 0 and "removed" in removed.stdout, removed.stderr
        out = await asyncio.wait_for(outcome, 90)
    finally:
        sp.stop()
    assert out == {"before": 0, "lost": True, "reconnected": False}, out  # 0: ServerState Running
