"""What the web HMI shows of a robot (``Companion.web_view``): found by type in any server; its history
view; the page draws it with ``static/view.js`` beside this module."""

from __future__ import annotations

from typing import Any

from asyncua import Client, ua

from uacell.binding.web_discovery import CONDITION_VARIABLES, Cell, Child, Discoverer
from uacell.binding.web_history import Window, program_runs, seconds, value_history

_CONDITION_TYPE = ua.NodeId(ua.ObjectIds.ConditionType)

# OPC 40010-1 method result Status names (docs/robotics.md), shown beside the number: the first
# output of the operation methods below (``Discoverer.methods(..., status=ROBOTICS_STATUS)``).
ROBOTICS_STATUS = {
    0: "OK",
    1: "E_SystemState",
    2: "E_UnexpectedError",
    3: "E_ActiveAlarm",
    4: "E_AcknowledgeRequired",
    -1: "not found",
    -2: "invalid content",
    -3: "unresolved reference",
    -4: "module in use",
}
SYSOP_METHODS = ("GetReady", "StandDown", "Start", "Stop")
# CurrentLine and ProgramPointer are uacell's own (docs/robotics.md): absent on other servers.
TASK_VARIABLES = ("TaskProgramName", "TaskProgramLoaded", "ExecutionMode", "CurrentLine", "ProgramPointer")
TASK_METHODS = ("LoadByName", "UnloadProgram", "UnloadByName", "Start", "Stop")


async def describe_robot(d: Discoverer, robot: Child, r: int) -> dict[str, Any]:
    """A robot: its controllers (SystemOperation, conditions, Programs, task controls, locks) and motion devices."""
    controllers = [
        await controller(d, f"{robot.name}/{c.name}", c, r)
        for c in await d.of_type(await d.child(robot.node, "Controllers"), ua.NodeId(1003, r))
    ]
    devices = []
    for device in await d.of_type(await d.child(robot.node, "MotionDevices"), ua.NodeId(1004, r)):
        prefix = f"{robot.name}/{device.name}"
        axes = []
        for axis in await d.of_type(await d.child(device.node, "Axes"), ua.NodeId(16601, r)):
            key = await d.variable(f"{prefix}/{axis.name}/ActualPosition", axis.node, "ParameterSet", "ActualPosition")
            if key:
                axes.append({"name": axis.name, "position": key})
        devices.append(
            {
                "name": device.name,
                "axes": axes,
                "in_control": await d.variable(f"{prefix}/InControl", device.node, "ParameterSet", "InControl"),
            }
        )
    return {"name": robot.name, "controllers": controllers, "motion_devices": devices}


async def controller(d: Discoverer, prefix: str, part: Child, r: int) -> dict[str, Any]:
    sysop = await d.child(part.node, "SystemOperation")
    machine = await d.child(sysop, "SystemOperationStateMachine")
    conditions = []
    for cond in await d.of_type(await d.child(sysop, "Conditions"), _CONDITION_TYPE):
        key = f"{prefix}/Conditions/{cond.name}"
        conditions.append(
            {
                "name": cond.name,
                "variables": {v: await d.variable(f"{key}/{v}", cond.node, *v.split("/")) for v in CONDITION_VARIABLES},
                "methods": await d.methods(key, cond.node, ("Acknowledge",)),
            }
        )
    programs = await d.child(part.node, "Programs")
    program_methods: dict[str, str] = {}
    if programs is not None:
        d.cell.directories[f"{prefix}/Programs"] = programs
        program_methods = await d.methods(f"{prefix}/Programs", programs, ("CreateFile", "Delete"))
    tasks = []
    for task in await d.of_type(await d.child(part.node, "TaskControls"), ua.NodeId(1011, r)):
        tasks.append(await task_control(d, f"{prefix}/{task.name}", task))
    sysop_prefix = f"{prefix}/SystemOperation"
    return {
        "name": part.name,
        "system_operation": {
            **await d.machine(sysop_prefix, machine),
            "substates": [
                await d.machine(f"{sysop_prefix}/{sub}", await d.child(machine, sub))
                for sub in ("IdleSubstateMachine", "ExecutingSubstateMachine")
            ],
            "methods": await d.methods(sysop_prefix, machine, SYSOP_METHODS, status=ROBOTICS_STATUS),
        },
        "conditions": conditions,
        "lock": await d.lock(prefix, part.node),
        "programs": f"{prefix}/Programs" if programs is not None else None,
        "program_methods": program_methods,
        "task_controls": tasks,
        "simulate_alarm": await d.method(f"{prefix}/SimulateAlarm", part.node, "SimulateAlarm"),
    }


async def task_control(d: Discoverer, prefix: str, task: Child) -> dict[str, Any]:
    machine = await d.child(task.node, "TaskControlOperation", "TaskControlStateMachine")
    ready = await d.child(machine, "ReadySubstateMachine")
    params = await d.child(task.node, "ParameterSet")
    modules = await d.child(task.node, "TaskModules")
    if modules is not None:
        d.cell.folders[f"{prefix}/TaskModules"] = modules
        d.cell.rebrowse = ("/TaskProgramName", "/CurrentState")
    methods = await d.methods(prefix, machine, TASK_METHODS, status=ROBOTICS_STATUS)
    methods |= await d.methods(f"{prefix}/ReadySubstateMachine", ready, ("ResetToProgramStart",), ROBOTICS_STATUS)
    return {
        "name": task.name,
        **await d.machine(prefix, machine),
        "ready": await d.machine(f"{prefix}/ReadySubstateMachine", ready),
        "variables": {n: await d.variable(f"{prefix}/{n}", params, n) for n in TASK_VARIABLES},
        "modules": f"{prefix}/TaskModules" if modules is not None else None,
        "lock": await d.lock(prefix, task.node),
        "methods": methods,
    }


async def robot_history(client: Client, cell: Cell, name: str, w: Window) -> dict[str, Any]:
    """The history view of a robot (``WebView.history``, uacell.web.history): each task control's
    program runs."""
    s, e = seconds(w.since), seconds(w.end)
    tasks = []
    for node_text, key in sorted(cell.machines.items(), key=lambda kv: kv[1]):
        if not (key.startswith(f"{name}/") and node_text.endswith(".TaskControlStateMachine")):
            continue
        state = cell.variables.get(f"{key}/CurrentState")
        program = cell.variables.get(f"{key}/TaskProgramName")
        states = await value_history(client, state, w.since, w.end) if state is not None else []
        programs = await value_history(client, program, w.since, w.end) if program is not None else []
        tasks.append({"task": key, "runs": [r.json() for r in program_runs(states, programs, s, e)]})
    return {"name": name, "tasks": tasks}
