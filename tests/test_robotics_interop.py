"""node-opcua drives the robot: GetReady, LoadByName, Start, and receives the task control's
TransitionEvents until the program ends by itself (ExecutingToReady, reason 5 Application)."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import ServeProcess, run_node, start_serve

pytestmark = pytest.mark.interop


@pytest.fixture
def fast_robot(tmp_path: Path) -> Iterator[ServeProcess]:
    """`uacell serve` with the simulated robot 20 times faster than real time."""
    config = tmp_path / "uacell.toml"
    config.write_text("[robot]\ntime_scale = 20.0\n", encoding="utf-8")
    sp = start_serve(tmp_path / "data", "--config", str(config))
    yield sp
    sp.stop()


def run_trusted(sp: ServeProcess, script: str, *args: str) -> dict[str, Any]:
    """Run a node-opcua script; if the server refused its certificate, trust it as an operator would
    (move it from pki/rejected to pki/trusted) and run again."""
    try:
        return run_node(script, sp.endpoint, *args)
    except AssertionError as first:
        rejected = sp.data_dir / "pki" / "rejected"
        moved = [shutil.move(f, sp.data_dir / "pki" / "trusted" / f.name) for f in rejected.glob("*")]
        if not moved or "BadCertificateUntrusted" not in str(first):
            raise
        return run_node(script, sp.endpoint, *args)


def test_node_opcua_runs_a_program_and_sees_every_transition(fast_robot):
    out = run_trusted(fast_robot, "robotics_run.js", "pick_and_place")
    assert (out["getReady"], out["loadGripper"], out["load"], out["start"]) == (0, 0, 0, 0)
    assert out["systemState"] == "Ready"
    assert out["programName"] == "PickAndPlace"
    transitions = [(e["transition"], e["from"], e["to"]) for e in out["events"]]
    assert transitions == [
        ("IdleToReady", "Idle", "Ready"),
        ("ReadyToExecuting", "Ready", "Executing"),
        ("ExecutingToReady", "Executing", "Ready"),
        ("ReadyToIdle", "Ready", "Idle"),  # UnloadProgram at the end
    ]
    assert out["otherEvents"] == 0
    # An AuditUpdateStateEvent (anonymous: ClientUserId null) after each transition a call caused,
    # none after the program's own end.
    audits = out["audits"]
    by_new_state = {e["toId"]: e for e in out["events"]}
    assert [(a["sourceName"], a["user"], a["status"]) for a in audits] == [
        ("Method/LoadByName", None, True),
        ("Method/Start", None, True),
        ("Method/UnloadProgram", None, True),
    ]
    for audit, event in zip(audits, [out["events"][0], out["events"][1], out["events"][3]], strict=True):
        assert (audit["oldId"], audit["newId"]) == (event["fromId"], event["toId"])
        assert audit["source"] == event["source"] and audit["serverId"] and audit["actionTime"]
        assert audit["newId"] in by_new_state
    assert audits[0]["inputs"] == ["pick_and_place"]  # loading the module gripper first took no transition
    assert (audits[1]["method"], audits[1]["inputs"]) == (out["startMethod"], [])
    assert audits[2]["method"] == out["unloadMethod"]
    # uacell's CurrentLine: lines while the program ran, 0 after it ended (UInt32, i=7).
    assert out["lineDataType"] == "ns=0;i=7"
    assert out["lineAfter"] == 0
    assert any(v > 0 for v in out["lines"]) and out["lines"][-1] == 0, out["lines"]
    # Transition/Id is the Transition node of the type (Robotics namespace), not a copy
    assert all(e["transitionId"] and ";i=" in e["transitionId"] for e in out["events"])
    assert (out["finalState"], out["reason"], out["readySubstate"]) == ("Ready", 5, "AtProgramStart")


def test_node_opcua_sees_the_caller_on_transitions_that_complete_after_the_call(tmp_path: Path):
    """GetReady, Stop and StandDown answer at once; the transition each asked for follows later and its
    AuditUpdateStateEvent names the call (decision 38)."""
    sp = start_serve(tmp_path / "data")
    try:
        out = run_trusted(sp, "audit_completion.js")
    finally:
        sp.stop()
    assert out["stop"] == 0
    methods = out["methods"]
    audits = {(a["machine"], a["sourceName"], a["method"]): a for a in out["audits"]}
    assert ("so", "Method/GetReady", methods["GetReady"]) in audits  # IdleToReady once the drives were on
    # ExecutingToReady once the robot had stopped, the task control's and the system's.
    stopped = audits[("tc", "Method/Stop", methods["Stop"])]
    assert ("so", "Method/Stop", methods["Stop"]) in audits
    assert stopped["inputs"] in ([4], [[0, 4]]), stopped  # StopMode QuickStop (Int64)
    assert ("so", "Method/StandDown", methods["StandDown"]) in audits  # ReadyToIdle once the drives were off
    assert all(a["user"] is None for a in out["audits"])  # an anonymous session: ClientUserId null
    assert all(a["oldId"] != a["newId"] for a in out["audits"])
