"""node-opcua sees `uacell serve` announce its stop on SIGTERM (OPC 10000-5 12.10; decision 85)."""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

import pytest
from conftest import INTEROP, start_serve

pytestmark = pytest.mark.interop


def test_node_opcua_sees_the_shutdown_announced_before_the_server_goes(tmp_path: Path) -> None:
    config = tmp_path / "uacell.toml"
    config.write_text("[server]\nshutdown_delay = 3\n")
    sp = start_serve(tmp_path / "data", "--config", str(config))
    node = subprocess.Popen(
        ["node", str(INTEROP / "shutdown.js"), sp.endpoint],
        cwd=INTEROP,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert node.stdout is not None
        line = node.stdout.readline()  # blocks until the subscription delivered (node-opcua's own timeouts bound it)
        assert line.strip() == "subscribed", (line, node.stderr.read() if node.stderr else "")
        assert sp.stop(signal.SIGTERM) == 0  # the client stays: the stop waits out the 3 s, then closes it
        out, err = node.communicate(timeout=90)
    finally:
        if node.poll() is None:
            node.kill()
            node.wait()
        sp.stop()
    result = json.loads([ln for ln in out.splitlines() if ln.startswith("{")][-1])
    assert result["states"][0] == 0  # Running
    assert 4 in result["states"], result  # Shutdown
    counted = [s for s in result["seconds"] if s]
    assert counted[:1] == [3] and counted == sorted(counted, reverse=True), result
    assert "uacell is stopping" in result["reasons"]
    assert result["end"] in ("connection_lost", "close"), (result, err)
