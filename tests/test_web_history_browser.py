"""The HMI's history view in headless Chromium: a unit's state timeline, trends and OEE, a robot's
program runs, readable at 1280x800 and on a phone (docs/web.md, "History")."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from asyncua import ua
from conftest import ServeProcess, start_serve, wait_for_web
from test_web_browser import CHROMIUM, DOCS, MACHINE, TIMEOUT, Ua, UaThread, browser, ua_thread  # noqa: F401

pytestmark = pytest.mark.skipif(not __import__("pathlib").Path(CHROMIUM).exists(), reason="Chromium is not installed")
EXEC = f"{MACHINE}.ExecuteState"
CTRL = "Robot1.Controllers.Controller1"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
TC = f"{CTRL}.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"
UNIT = 'article.hist-unit[data-unit="Filler1"]'


@pytest.fixture(scope="module")
def serve(tmp_path_factory) -> Iterator[ServeProcess]:
    data = tmp_path_factory.mktemp("web-history") / "data"
    config = data.parent / "uacell.toml"
    config.write_text(
        "[packml]\nacting_time = 0.2\nmach_speed = 120.0\n"
        "[robot]\ntime_scale = 50.0\n"
        "[history]\nflush_interval = 0.05\n"
    )
    sp = start_serve(data, "--config", str(config), web=True)
    sp.web = wait_for_web(sp)
    yield sp
    assert sp.stop() == 0


def run_the_filler(serve: ServeProcess, thread: UaThread) -> None:
    """Reset, Start, a new speed, Hold: states, speeds and counts for the history."""

    async def go() -> None:
        async with Ua(serve.endpoint) as c:
            await c.filler_to_stopped()
            assert (await c.call(MACHINE, "Reset")).StatusCode.is_good()
            await c.wait_state(EXEC, "Idle")
            start = await c.call(EXEC, "Start", ua.Variant([], ua.VariantType.ExtensionObject, is_array=True))
            assert start.StatusCode.is_good(), start
            await c.wait_state(EXEC, "Execute")
            speed = await c.call("Filler1", "SetMachSpeed", ua.Variant(300.0, ua.VariantType.Float))
            assert speed.StatusCode.is_good()
            assert (await c.call(EXEC, "Hold")).StatusCode.is_good()
            await c.wait_state(EXEC, "Held")

    thread.run(go())


def run_a_program(serve: ServeProcess, thread: UaThread) -> None:
    """Robot1 runs pick_and_place (PickAndPlace) once (CYCLE) to its end: one program run for the history."""

    def ok(res: ua.CallMethodResult) -> None:
        assert res.StatusCode.is_good() and res.OutputArguments[0].Value == 0, res

    async def go() -> None:
        async with Ua(serve.endpoint) as c:
            ok(await c.call(SO, "GetReady"))
            await c.wait_state(SO, "Ready")
            for name in ("gripper", "pick_and_place"):  # the module it calls, then the program
                ok(await c.call(TC, "LoadByName", ua.Variant(name, ua.VariantType.String)))
            ok(await c.call(TC, "Start"))
            await c.wait_state(TC, "Executing")
            await c.wait_state(TC, "Ready", timeout=60.0)  # the end of the program

    thread.run(go(), timeout=120.0)


def test_history_view_shows_timeline_trends_oee_and_program_runs(browser, serve, ua_thread):  # noqa: F811
    run_the_filler(serve, ua_thread)
    run_a_program(serve, ua_thread)
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(serve.web)
    page.wait_for_selector("#conn[data-status=connected]", timeout=TIMEOUT)
    page.click("#history-refresh")
    page.wait_for_selector(f'{UNIT} svg.hist-bar rect[data-state="Held"]', timeout=TIMEOUT)
    states = page.locator(f"{UNIT} svg.hist-bar rect").evaluate_all("rs => rs.map(r => r.dataset.state)")
    # the timeline holds the run in order: ... Idle, Starting, Execute, Holding, Held
    order = [s for s in states if s in ("Idle", "Starting", "Execute", "Holding", "Held")]
    assert order[-5:] == ["Idle", "Starting", "Execute", "Holding", "Held"], states
    rows = page.locator(f"{UNIT} table.hist-states tr[data-state]").evaluate_all("rs => rs.map(r => r.dataset.state)")
    assert rows[0] == "Held" and "Execute" in rows  # which state, newest first, with when and how long
    assert page.locator(f"{UNIT} table.hist-states tr[data-state=Execute] td").nth(3).inner_text().endswith("s")
    speeds = page.locator(f'{UNIT} polyline[data-series="MachSpeed"]')
    assert speeds.count() == 1
    assert "now 300" in page.locator(f'{UNIT} .hist-legend span[data-series="MachSpeed"]').inner_text()
    figures = {
        name: page.inner_text(f'{UNIT} dl.oee [data-figure="{name}"] dd')
        for name in ("Availability", "Performance", "Quality", "OEE")
    }
    assert all(v.endswith("%") for v in figures.values()), figures
    robot = 'article.hist-robot[data-robot="Robot1"]'
    page.wait_for_selector(f'{robot} li[data-program="PickAndPlace"]', timeout=TIMEOUT)
    assert page.locator(f'{robot} svg.hist-bar rect[data-state="PickAndPlace"]').count() == 1
    assert "PickAndPlace: " in page.inner_text(f"{robot} ul.hist-runs")
    page.locator("#history").screenshot(path=str(DOCS / "web-history.png"))
    # a phone: nothing wider than the screen
    page.set_viewport_size({"width": 390, "height": 844})
    page.click("#history-refresh")
    page.wait_for_selector(f'{UNIT} svg.hist-bar rect[data-state="Held"]', timeout=TIMEOUT)
    assert page.evaluate("() => document.querySelector('#history').scrollWidth <= window.innerWidth")
    context.close()
    assert not errors, errors
