"""Running uacell as a service: audit trail, metrics, sd_notify, health check, systemd unit, container.

One in-process server with metrics on (module scope), driven by real asyncua clients over TCP; the
service-manager side runs `uacell serve` as a subprocess.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import ROOT, fast_config, start_app, start_serve
from helpers import free_port

from uacell.core.notify import notify
from uacell.server import UacellServer

module_loop = pytest.mark.asyncio(loop_scope="module")

CTRL = "Robot1.Controllers.Controller1"
TC = f"{CTRL}.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"
PROGRAMS = f"{CTRL}.Programs"
PASSWORD = "correct horse battery"
TIMEOUT = 30.0


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def app(tmp_path_factory):
    config = fast_config(tmp_path_factory.mktemp("ops") / "data")
    config.metrics.enabled = True
    config.metrics.port = free_port()
    server = await start_app(config)
    server.users.add("eve", "engineer", PASSWORD)
    try:
        yield server
    finally:
        await server.stop()


def audit_lines(app: UacellServer) -> list[dict[str, Any]]:
    path = app.data_dir / "audit.log"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


async def wait_for_audit(app: UacellServer, predicate, timeout: float = TIMEOUT) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for entry in audit_lines(app):
            if predicate(entry):
                return entry
        await asyncio.sleep(0.05)
    raise AssertionError(f"no such audit line in {audit_lines(app)}")


def nid(app: UacellServer, path: str) -> ua.NodeId:
    return ua.NodeId(path, app.cell.instantiator.ns)


async def call(client: Client, obj: ua.NodeId, method: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
    req = ua.CallMethodRequest()
    req.ObjectId, req.MethodId, req.InputArguments = obj, method, list(args)
    (res,) = await client.uaclient.call([req])
    return res


async def call_named(app: UacellServer, client: Client, obj_path: str, name: str, *args: ua.Variant):
    obj = nid(app, obj_path)
    return obj, await call(client, obj, app.dispatcher.method_of(obj, name), *args)


# --- audit trail -----------------------------------------------------------------------------------------


@module_loop
async def test_audit_records_a_login_failure_with_user_address_and_application_uri(app):
    client = Client(app.endpoint, timeout=20)
    client.application_uri = "urn:test:audit-client"
    client.set_user("eve")
    client.set_password("wrong password")
    with pytest.raises(ua.UaStatusCodeError) as err:
        await client.connect()
    assert err.value.code == ua.StatusCodes.BadUserAccessDenied
    app.security.throttle.succeeded("eve", "127.0.0.1")
    entry = await wait_for_audit(app, lambda e: e["event"] == "login" and e["result"] != "Good")
    assert entry["user"] == "eve"
    assert entry["result"] == "BadUserAccessDenied"
    assert entry["address"] == "127.0.0.1"
    assert entry["application_uri"] == "urn:test:audit-client"
    assert "wrong password" not in (app.data_dir / "audit.log").read_text()


@module_loop
async def test_audit_records_login_session_open_and_close(app):
    client = Client(app.endpoint, timeout=20)
    client.application_uri = "urn:test:audit-ok"
    client.set_user("eve")
    client.set_password(PASSWORD)
    await client.connect()
    await client.disconnect()
    mine = lambda e: e.get("application_uri") == "urn:test:audit-ok"  # noqa: E731
    login = await wait_for_audit(app, lambda e: mine(e) and e["event"] == "login")
    assert (login["user"], login["result"], login["address"]) == ("eve", "Good", "127.0.0.1")
    opened = await wait_for_audit(app, lambda e: mine(e) and e["event"] == "session_open")
    closed = await wait_for_audit(app, lambda e: mine(e) and e["event"] == "session_close")
    assert opened["session"] == closed["session"] and closed["user"] == "eve"


@module_loop
async def test_audit_records_a_refused_call_and_a_call_with_its_status_output(app):
    async with Client(app.endpoint, timeout=20) as client:  # anonymous: operator on loopback
        obj, refused = await call_named(
            app,
            client,
            CTRL,
            "SimulateAlarm",
            ua.Variant("Overheat", ua.VariantType.String),
            ua.Variant(True, ua.VariantType.Boolean),
        )
        assert refused.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
        entry = await wait_for_audit(app, lambda e: e["event"] == "call" and e["method"] == "SimulateAlarm")
        assert entry["user"] == "anonymous" and entry["role"] == "operator"
        assert entry["object"] == obj.to_string()
        assert entry["result"] == "BadUserAccessDenied"

        tc, res = await call_named(app, client, TC, "LoadByName", ua.Variant("no_such_program", ua.VariantType.String))
        entry = await wait_for_audit(app, lambda e: e["event"] == "call" and e["method"] == "LoadByName")
        assert entry["object"] == tc.to_string()
        assert entry["result"] == res.StatusCode.name
        if res.OutputArguments:
            assert entry["status_output"] == res.OutputArguments[0].Value


@module_loop
async def test_audit_records_a_program_upload_and_writes(app):
    client = Client(app.endpoint, timeout=20)
    client.set_user("eve")
    client.set_password(PASSWORD)
    await client.connect()
    try:
        _, res = await call_named(
            app,
            client,
            PROGRAMS,
            "CreateFile",
            ua.Variant("audited.robot", ua.VariantType.String),
            ua.Variant(True, ua.VariantType.Boolean),
        )
        assert res.StatusCode.is_good(), res.StatusCode
        file_id, handle = res.OutputArguments[0].Value, res.OutputArguments[1].Value
        node = client.get_node(file_id)
        write = (await node.get_child("0:Write")).nodeid
        close = (await node.get_child("0:Close")).nodeid
        h = ua.Variant(handle, ua.VariantType.UInt32)
        assert (
            await call(client, file_id, write, h, ua.Variant(b"move home\n", ua.VariantType.ByteString))
        ).StatusCode.is_good()
        assert (await call(client, file_id, close, h)).StatusCode.is_good()

        created = await wait_for_audit(
            app, lambda e: e["event"] == "program_file" and e["path"] == "audited.robot" and e["operation"] == "added"
        )
        assert created["user"] == "eve"
        # the trail is written every FLUSH_INTERVAL: wait for the last of the three calls
        await wait_for_audit(app, lambda e: e["event"] == "call" and e["user"] == "eve" and e["method"] == "Close")
        calls = [e for e in audit_lines(app) if e["event"] == "call" and e["user"] == "eve"]
        assert [e["method"] for e in calls][-3:] == ["CreateFile", "Write", "Close"]
        assert all(e["result"] == "Good" for e in calls[-3:])

        # a write: refused for an operator, recorded with its result
        speed = app.cell.instantiator.ns
        target = ua.NodeId("Filler1.Status.MachSpeed", speed)
        params = ua.WriteParameters()
        params.NodesToWrite = [
            ua.WriteValue(
                NodeId=target,
                AttributeId=ua.AttributeIds.Value,
                Value=ua.DataValue(ua.Variant(12.5, ua.VariantType.Float)),
            )
        ]
    finally:
        await client.disconnect()
    async with Client(app.endpoint, timeout=20) as anonymous:
        (status,) = await anonymous.uaclient.write(params)
    entry = await wait_for_audit(app, lambda e: e["event"] == "write" and e["node"] == target.to_string())
    assert entry["user"] == "anonymous" and entry["attribute"] == "Value" and entry["value"] == 12.5
    assert entry["result"] == status.name


# --- metrics --------------------------------------------------------------------------------------------


async def scrape(app: UacellServer, path: str = "/metrics") -> tuple[str, str]:
    assert app.metrics is not None  # the test configuration serves metrics
    reader, writer = await asyncio.open_connection("127.0.0.1", app.metrics.port)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: localhost\r\n\r\n".encode())
    await writer.drain()
    data = await reader.read()
    writer.close()
    head, _, body = data.decode().partition("\r\n\r\n")
    return head.split("\r\n", 1)[0], body


def sample(body: str, metric: str, **labels: str) -> float | None:
    for line in body.splitlines():
        if line.startswith("#"):
            continue
        m = re.fullmatch(r"([a-zA-Z_:][\w:]*)(?:\{(.*)\})? (\S+)", line)
        if not m or m.group(1) != metric:
            continue
        have = dict(re.findall(r'(\w+)="((?:[^"\\]|\\.)*)"', m.group(2) or ""))
        if all(have.get(k) == v for k, v in labels.items()):
            return float(m.group(3))
    return None


@module_loop
async def test_metrics_endpoint_is_off_by_default_and_loopback_when_on():
    from uacell.config import Config

    assert Config().metrics.enabled is False and Config().metrics.host == "127.0.0.1"


@module_loop
async def test_metrics_values_move_with_a_call(app):
    status, before = await scrape(app)
    assert status == "HTTP/1.1 200 OK"
    async with Client(app.endpoint, timeout=20) as client:
        _, during = await scrape(app)
        sessions = sample(during, "uacell_sessions")
        assert sessions is not None and sessions >= 1
        reset = next(b for b in app.dispatcher.methods.values() if b.name == "Reset")
        res = await call(client, reset.object_id, reset.method_id)
    result = res.StatusCode.name
    _, after = await scrape(app)
    calls = lambda body: sample(body, "uacell_calls_total", method="Reset", result=result) or 0.0  # noqa: E731
    count = lambda body: sample(body, "uacell_call_duration_seconds_count", method="Reset") or 0.0  # noqa: E731
    assert calls(after) == calls(before) + 1
    assert count(after) == count(before) + 1
    # each state machine's current state, as clients read it
    async with Client(app.endpoint, timeout=20) as client:
        current = await client.get_node(nid(app, "Filler1.BaseStateMachine.CurrentState")).read_value()
        task_control = await client.get_node(nid(app, f"{TC}.CurrentState")).read_value()
    assert sample(after, "uacell_state_machine_state", machine="Filler1.BaseStateMachine", state=current.Text) == 1.0
    assert sample(after, "uacell_state_machine_state", machine=TC, state=task_control.Text) == 1.0
    missing, _ = await scrape(app, "/nothing")
    assert missing == "HTTP/1.1 404 Not Found"


@module_loop
async def test_metrics_show_the_packml_counters(app):
    _, body = await scrape(app)
    async with Client(app.endpoint, timeout=20, watchdog_intervall=30.0) as client:
        await client.load_data_type_definitions()
        processed = await client.get_node(nid(app, "Filler1.Admin.ProdProcessedCount")).read_value()
    assert processed, "the demo unit has processed-count entries"
    for item in processed:
        labels = {"unit": "Filler1", "counter": "ProdProcessedCount", "id": str(item.ID), "name": item.Name}
        assert sample(body, "uacell_packml_count", **labels) == float(item.Count)
        assert sample(body, "uacell_packml_acc_count", **labels) == float(item.AccCount)


# --- sd_notify ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("abstract", [False, True])
def test_notify_writes_a_datagram_to_the_socket(tmp_path, abstract):
    name = f"@uacell-test-{os.getpid()}-{time.monotonic_ns()}" if abstract else str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name[1:] if abstract else name)
        sock.settimeout(10)
        assert notify("READY=1", {"NOTIFY_SOCKET": name}) is True
        assert sock.recv(1024) == b"READY=1"
    assert notify("READY=1", {}) is False
    assert notify("READY=1", {"NOTIFY_SOCKET": "relative/path"}) is False


def test_serve_tells_systemd_when_it_listens_and_when_it_stops(tmp_path):
    path = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(path))
        sock.settimeout(60)
        sp = start_serve(tmp_path / "data", env={"NOTIFY_SOCKET": str(path)})
        try:
            ready = sock.recv(1024).decode()
            assert ready.splitlines()[0] == "READY=1"
            assert f"STATUS=listening on {sp.endpoint}" in ready
        finally:
            rc = sp.stop(signal.SIGTERM)
        assert sock.recv(1024) == b"STOPPING=1"
    assert rc == 0


# --- health check (what the container image runs) --------------------------------------------------------


def test_health_command_answers_running_for_a_live_server_and_fails_otherwise(tmp_path, serve_process):
    ok = subprocess.run(
        [sys.executable, "-m", "uacell", "health", "--endpoint", serve_process.endpoint],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.strip() == f"uacell: {serve_process.endpoint}: Running"
    port = serve_process.endpoint.rsplit(":", 1)[1].strip("/")
    # the same check through the configuration a container uses (UACELL_CONFIG)
    cfg = tmp_path / "uacell.toml"
    cfg.write_text(f"[server]\nhost = '0.0.0.0'\nport = {port}\n")
    via_config = subprocess.run(
        [sys.executable, "-m", "uacell", "health"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env={**os.environ, "UACELL_CONFIG": str(cfg)},
    )
    assert via_config.returncode == 0, via_config.stderr
    down = subprocess.run(
        [
            sys.executable,
            "-m",
            "uacell",
            "health",
            "--endpoint",
            f"opc.tcp://127.0.0.1:{free_port()}/",
            "--timeout",
            "5",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert down.returncode == 1
    assert "Traceback" not in down.stderr and down.stderr.startswith("uacell: opc.tcp://127.0.0.1:")


# --- deployment files -----------------------------------------------------------------------------------


def test_systemd_unit_verifies(tmp_path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed")
    unit = (ROOT / "deploy" / "uacell.service").read_text()
    assert "Type=notify" in unit and "NoNewPrivileges=yes" in unit and "ProtectSystem=strict" in unit
    # verify needs the ExecStart binary to exist: point it at this checkout's uacell
    exe = Path(sys.executable).parent / "uacell"
    local = tmp_path / "uacell.service"
    local.write_text(unit.replace("/opt/uacell/bin/uacell", str(exe)))
    proc = subprocess.run([analyze, "verify", str(local)], capture_output=True, text=True, timeout=120, check=False)
    problems = [ln for ln in proc.stderr.splitlines() if "uacell.service" in ln]
    assert proc.returncode == 0 and not problems, proc.stderr


def test_container_entry_point_and_health_check_are_the_tested_commands():
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert 'ENTRYPOINT ["uacell"]' in dockerfile
    assert 'CMD ["serve"]' in dockerfile
    assert "HEALTHCHECK" in dockerfile and 'CMD ["uacell", "health"]' in dockerfile
    assert "RUN uacell models fetch" in dockerfile
    assert re.search(r"^USER uacell$", dockerfile, re.M)
    assert 'VOLUME ["/var/lib/uacell"]' in dockerfile


def test_container_image_builds_and_serves():
    docker = shutil.which("docker")
    if docker is None:
        pytest.skip("no docker CLI")
    info = subprocess.run([docker, "info"], capture_output=True, text=True, timeout=60, check=False)
    if info.returncode != 0:
        pytest.skip("no container engine answers `docker info`")
    tag = f"uacell-test:{os.getpid()}"
    build = subprocess.run(
        [docker, "build", "-t", tag, str(ROOT)], capture_output=True, text=True, timeout=1800, check=False
    )
    assert build.returncode == 0, build.stderr[-4000:]
    port = free_port()
    name = f"uacell-test-{os.getpid()}"
    run = subprocess.run(
        [docker, "run", "-d", "--rm", "--name", name, "-p", f"127.0.0.1:{port}:4840", tag],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            health = subprocess.run(
                [sys.executable, "-m", "uacell", "health", "--endpoint", f"opc.tcp://127.0.0.1:{port}/"],
                capture_output=True,
                text=True,
                timeout=60,
                check=False,
            )
            if health.returncode == 0:
                break
            time.sleep(1)
        assert health.returncode == 0, health.stderr
    finally:
        subprocess.run([docker, "stop", "-t", "30", name], capture_output=True, timeout=120, check=False)
        subprocess.run([docker, "rmi", tag], capture_output=True, timeout=120, check=False)


# --- logging ----------------------------------------------------------------------------------------------


def test_log_file_rotates_and_per_logger_levels_apply(tmp_path):
    import logging

    from uacell.config import Config
    from uacell.core import logs

    config = Config()
    config.logging.file = tmp_path / "logs" / "uacell.log"
    config.logging.max_bytes = 1024
    config.logging.backups = 2
    config.logging.format = "json"
    config.logging.levels = {"uacell.test.quiet": "ERROR"}
    root = logging.getLogger()
    saved = (root.level, list(root.handlers))
    try:
        logs.configure(config)
        for i in range(200):
            logging.getLogger("uacell.test.loud").info("line %d of the rotation test", i)
            logging.getLogger("uacell.test.quiet").warning("never written")
        for h in root.handlers:
            h.flush()
    finally:
        logs.configure_console("WARNING")
        root.setLevel(saved[0])
    files = sorted(p.name for p in (tmp_path / "logs").iterdir())
    assert files == ["uacell.log", "uacell.log.1", "uacell.log.2"]
    lines = [json.loads(ln) for ln in (tmp_path / "logs" / "uacell.log").read_text().splitlines()]
    assert lines and all(e["logger"] == "uacell.test.loud" and e["level"] == "INFO" for e in lines)
    assert lines[-1]["message"] == "line 199 of the rotation test"
    assert "never written" not in "".join(p.read_text() for p in (tmp_path / "logs").iterdir())


def test_audit_trail_writes_in_batches_rotates_and_loses_nothing_on_close(tmp_path):
    from uacell.security.audit import AuditTrail

    path = tmp_path / "audit" / "audit.log"
    trail = AuditTrail(path, max_bytes=2048, backups=3, flush_interval=60.0)  # the thread never wakes here
    for i in range(60):
        trail.record("call", user="alice", n=i, method="LoadByName")
    assert not path.exists() or path.read_text() == ""  # held in memory until the interval or close
    trail.close()
    files = sorted(p.name for p in path.parent.iterdir())
    assert files == ["audit.log", "audit.log.1", "audit.log.2", "audit.log.3"]
    assert all(p.stat().st_size <= 2048 for p in path.parent.iterdir())
    kept = []
    for name in ("audit.log.3", "audit.log.2", "audit.log.1", "audit.log"):  # oldest first
        kept += [json.loads(ln) for ln in (path.parent / name).read_text().splitlines()]
    numbers = [e["n"] for e in kept]
    assert numbers == list(range(60 - len(numbers), 60))  # in order, the newest kept, none twice
    assert kept[-1]["event"] == "call" and kept[-1]["user"] == "alice" and kept[-1]["time"].endswith("+00:00")


async def test_audit_trail_reaches_the_file_within_its_interval_while_running(tmp_path):
    from uacell.security.audit import AuditTrail

    path = tmp_path / "audit.log"
    trail = AuditTrail(path, flush_interval=0.05)
    try:
        trail.record("write", user="bob", node="ns=1;s=X")
        deadline = time.monotonic() + TIMEOUT
        while not path.read_text() and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        (line,) = path.read_text().splitlines()
        assert json.loads(line)["node"] == "ns=1;s=X"
    finally:
        trail.close()


async def test_serve_stopped_by_sigterm_has_written_every_call_record(tmp_path):
    sp = start_serve(tmp_path / "data")
    try:
        async with Client(sp.endpoint, timeout=20) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            filler = client.get_node(ua.NodeId("Filler1", ns))
            speed = client.get_node(ua.NodeId("Filler1.SetMachSpeed", ns))
            for value in range(1, 21):
                await filler.call_method(speed, ua.Variant(float(value), ua.VariantType.Float))
    finally:
        assert sp.stop(signal.SIGTERM) == 0
    audit = [json.loads(ln) for ln in (tmp_path / "data" / "audit.log").read_text().splitlines()]
    assert [e["result"] for e in audit if e["event"] == "call" and e["method"] == "SetMachSpeed"] == ["Good"] * 20


async def test_serve_logs_json_and_a_refused_login_is_one_info_line(tmp_path):
    log_file = tmp_path / "uacell.log"
    sp = start_serve(tmp_path / "data", "--log-format", "json", "--log-level", "INFO", "--log-file", str(log_file))
    try:
        client = Client(sp.endpoint, timeout=20)
        client.set_user("nobody")
        client.set_password("wrong password")
        with pytest.raises(ua.UaStatusCodeError):
            await client.connect()
    finally:
        assert sp.stop() == 0
    out = "".join(sp.output)
    entries = [json.loads(ln) for ln in out.splitlines() if ln.startswith("{")]
    assert entries, out
    refusals = [e for e in entries if "refused login of user 'nobody'" in e["message"]]
    assert [e["level"] for e in refusals] == ["INFO"]
    assert not [e for e in entries if e["level"] in ("ERROR", "CRITICAL")], out
    assert "Traceback" not in out
    in_file = [json.loads(ln) for ln in log_file.read_text().splitlines()]
    assert any("refused login of user 'nobody'" in e["message"] for e in in_file)
    audit = [json.loads(ln) for ln in (tmp_path / "data" / "audit.log").read_text().splitlines()]
    assert [(e["event"], e["user"], e["result"]) for e in audit if e["event"] == "login"] == [
        ("login", "nobody", "BadUserAccessDenied")
    ]


def test_a_metrics_port_in_use_is_one_clear_line(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        cfg = tmp_path / "uacell.toml"
        cfg.write_text(f"[metrics]\nenabled = true\nport = {port}\n")
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "uacell",
                "serve",
                "--port",
                str(free_port()),
                "--data-dir",
                str(tmp_path / "d"),
                "--config",
                str(cfg),
                "--log-level",
                "ERROR",
            ],
            capture_output=True,
            text=True,
            timeout=180,
            check=False,
        )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith(f"uacell: cannot serve metrics on 127.0.0.1:{port}")
    assert "Traceback" not in proc.stderr
