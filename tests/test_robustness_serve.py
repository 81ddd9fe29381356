"""Issue-12 finding 1 against a real `uacell serve`: a hostile program is refused at once while other
clients keep being served, a program of instant steps cannot starve the loop, and SIGTERM ends the
process within 5 s."""

from __future__ import annotations

import asyncio
import signal
import time
from pathlib import Path

from asyncua import Client, ua
from conftest import start_serve
from helpers import raw_call

from uacell.robotics.equipment import ExecutionMode

CTRL = "Robot1.Controllers.Controller1"
TASK = f"{CTRL}.TaskControls.TaskControl1"
TC = f"{TASK}.TaskControlOperation.TaskControlStateMachine"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
SPIN3 = "program Spin3\nrepeat 10000\nrepeat 10000\nrepeat 10000\nspeed 50\nend\nend\nend\n"
DEEP = "program Deep\n" + "repeat 2\n" * 4000 + "wait 0\n" + "end\n" * 4000
INSTANT = "program Instant\nwait 0\n"


async def _call(client: Client, ns: int, path: str, method: str, *args: ua.Variant) -> int:
    res = await raw_call(client, ua.NodeId(path, ns), ua.NodeId(f"{path}.{method}", ns), *args)
    assert res.StatusCode.is_good(), (method, res.StatusCode)
    return res.OutputArguments[0].Value


async def _state(client: Client, ns: int, path: str) -> str:
    return (await client.get_node(ua.NodeId(f"{path}.CurrentState", ns)).read_value()).Text


async def _scenario(endpoint: str) -> None:
    async with Client(endpoint, timeout=30) as a, Client(endpoint, timeout=30) as b:
        ns = await a.get_namespace_index("urn:uacell:cell")
        name = ua.Variant
        for program in ("spin3", "deep"):
            started = time.monotonic()
            load = asyncio.create_task(_call(a, ns, TC, "LoadByName", name(program, ua.VariantType.String)))
            # Another client is served while the load is checked.
            while not load.done():
                t0 = time.monotonic()
                await b.nodes.server_state.read_value()
                assert time.monotonic() - t0 < 2.0
                await asyncio.sleep(0.02)
            assert await load == -2
            assert time.monotonic() - started < 10.0
        assert await _call(a, ns, SO, "GetReady") == 0
        async with asyncio.timeout(20):
            while await _state(a, ns, SO) != "Ready":
                await asyncio.sleep(0.05)
        mode = a.get_node(ua.NodeId(f"{TASK}.ParameterSet.ExecutionMode", ns))
        await mode.write_value(ua.Variant(int(ExecutionMode.CONTINUOUS), ua.VariantType.Int32))
        assert await _call(a, ns, TC, "LoadByName", name("instant", ua.VariantType.String)) == 0
        assert await _call(a, ns, TC, "Start") == 0
        assert await _state(a, ns, TC) == "Executing"
        worst = 0.0
        for _ in range(20):
            t0 = time.monotonic()
            await b.nodes.server_state.read_value()
            worst = max(worst, time.monotonic() - t0)
        assert worst < 2.0
        assert await _state(a, ns, TC) == "Executing"


def test_hostile_programs_are_refused_and_sigterm_stops_a_busy_server_within_5_s(tmp_path: Path) -> None:
    data = tmp_path / "data"
    programs = data / "programs"
    programs.mkdir(parents=True)
    for file, text in {"spin3.robot": SPIN3, "deep.robot": DEEP, "instant.robot": INSTANT}.items():
        (programs / file).write_text(text)
    config = tmp_path / "uacell.toml"
    config.write_text("[robot]\ntime_scale = 50.0\n")
    sp = start_serve(data, "--config", str(config))
    try:
        asyncio.run(_scenario(sp.endpoint))
        assert sp.proc.poll() is None
        started = time.monotonic()
        rc = sp.stop(signal.SIGTERM, timeout=5.0)
        assert time.monotonic() - started < 5.0
        assert rc == 0, "".join(sp.output)
    finally:
        sp.stop(signal.SIGKILL)
        if sp.proc.stdout is not None:
            sp.proc.stdout.close()
