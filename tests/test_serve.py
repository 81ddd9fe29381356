"""`uacell serve` as a user runs it: listening line, clean exit, clear errors; node-opcua browses it."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest
from conftest import run_node, start_serve
from helpers import free_port


def test_serve_prints_listening_line_and_exits_cleanly_on_sigint(tmp_path):
    sp = start_serve(tmp_path / "data")  # a fresh data directory, logging at WARNING
    assert sp.endpoint.startswith("opc.tcp://127.0.0.1:")
    assert [line for line in sp.output if "WARNING" in line] == []  # a normal first start warns of nothing
    rc = sp.stop(signal.SIGINT)
    assert rc == 0
    assert "Traceback" not in "".join(sp.output)


def test_serve_exits_zero_on_sigterm(serve_process):
    assert serve_process.stop(signal.SIGTERM) == 0
    assert "Traceback" not in "".join(serve_process.output)


def test_port_in_use_is_one_clear_line(serve_process, tmp_path):
    port = serve_process.endpoint.rsplit(":", 1)[1].strip("/")
    proc = subprocess.run(
        [sys.executable, "-m", "uacell", "serve", "--port", port, "--data-dir", str(tmp_path / "other")],
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    assert proc.returncode == 2
    assert f"uacell: cannot listen on 127.0.0.1:{port}: address already in use" in proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (None, "cannot read configuration"),
        ("[server\nport = 1", "is not valid TOML"),
        ("[server]\nport = 'x'", "[server] port: must be an integer"),
        ("[nonsense]\na = 1", "[nonsense]: unknown section"),
    ],
)
def test_unreadable_configuration_is_one_clear_line(tmp_path, content, expected):
    cfg = tmp_path / "uacell.toml"
    if content is not None:
        cfg.write_text(content)
    proc = subprocess.run(
        [sys.executable, "-m", "uacell", "serve", "--config", str(cfg), "--port", str(free_port())],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0] and lines[0].startswith("uacell: ")


@pytest.mark.interop
def test_node_opcua_browses_to_the_state_machines_and_reads_arguments(serve_process):
    out = run_node("browse.js", serve_process.endpoint)
    ns = out["namespaces"]
    assert out["walked"][-1] == "TaskControlStateMachine"
    assert out["loadByNodeId"] == [{"name": "Id", "dataType": "ns=0;i=18", "valueRank": -1}]
    assert out["start"] == [{"name": "Parameter", "dataType": f"ns={ns['PackML']};i=16", "valueRank": 1}]
    assert out["executeStateType"] == [f"ns={ns['PackML']};i=1"]


@pytest.mark.interop
def test_node_opcua_sees_the_precise_argument_error_codes(serve_process):
    out = run_node("argument_errors.js", serve_process.endpoint)
    r = out["results"]
    assert r["missing"] == {"status": "BadArgumentsMissing", "inputArgumentResults": []}
    assert r["tooMany"]["status"] == "BadTooManyArguments"
    assert r["wrongType"] == {"status": "BadTypeMismatch", "inputArgumentResults": ["BadTypeMismatch"]}
    assert r["wrongIdType"] == {"status": "BadTypeMismatch", "inputArgumentResults": ["BadTypeMismatch"]}
    assert r["stopModeInt32"] == {"status": "BadTypeMismatch", "inputArgumentResults": ["BadTypeMismatch"]}
    assert r["startScalar"] == {"status": "BadTypeMismatch", "inputArgumentResults": ["BadTypeMismatch"]}
    assert r["startInt32Array"] == {"status": "BadTypeMismatch", "inputArgumentResults": ["BadTypeMismatch"]}
    assert r["wrongObject"]["status"] == "BadMethodInvalid"
    assert out["before"] == out["after"] == "Idle"


@pytest.mark.parametrize("delay", [0.5, 2.0])
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_request_during_start_up_exits_zero_quietly(tmp_path, sig, delay):
    """Ctrl-C or SIGTERM before the listening line (importing, loading models, building the cell)."""
    import time

    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "uacell",
            "serve",
            "--port",
            str(free_port()),
            "--data-dir",
            str(tmp_path / "d"),
            "--no-web",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    time.sleep(delay)
    proc.send_signal(sig)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, out
    assert "Traceback" not in out


def test_a_data_directory_that_cannot_be_made_is_one_clear_line(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    proc = subprocess.run(
        [sys.executable, "-m", "uacell", "serve", "--port", str(free_port()), "--data-dir", str(blocker / "data")],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("uacell: cannot create data directory"), proc.stderr
