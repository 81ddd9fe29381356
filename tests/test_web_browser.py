"""The web HMI in a real headless browser (Debian's Chromium driven by Playwright).

One `uacell serve` (with the HMI beside it, as a user runs it) serves the demo cell for the module;
each test opens a fresh browser context (its own cookies, so its own web and OPC UA session). The
page is driven like a person would; what arrived is checked in the page and, through an OPC UA
client, in the server. Screenshots land in a temporary folder; `make screenshots` (UACELL_SCREENSHOTS=docs)
writes them into docs/, where docs/web.md shows them.
"""

from __future__ import annotations

import asyncio
import os
import re
import shutil
import tempfile
import threading
import time
from collections.abc import Coroutine, Iterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from conftest import ROOT, ServeProcess, start_serve, wait_for_web
from helpers import CellClient, raw_call

from uacell.security.users import UserStore

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
pytestmark = pytest.mark.skipif(
    not Path(CHROMIUM).exists(), reason="Chromium is not installed (make setup installs it where it can)"
)

ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
PASSWORD = "pw-browser-1"
# A clean checkout stays clean: the docs' pictures are renewed only on request.
DOCS = Path(os.environ.get("UACELL_SCREENSHOTS") or tempfile.mkdtemp(prefix="uacell-shots-"))
if not DOCS.is_absolute():
    DOCS = ROOT / DOCS
MACHINE = "Filler1.BaseStateMachine.MachineState"
CTRL = "Robot1.Controllers.Controller1"
TIMEOUT = 30_000  # ms, for conditions that take the simulators' time


class UaThread:
    """An event loop in a thread, so that sync tests can hold OPC UA sessions open while they browse."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def run(self, coro: Coroutine[Any, Any, Any], timeout: float = 120.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def close(self) -> None:
        async def drain() -> None:  # what stopped servers and clients left behind
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        self.run(drain(), 30)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


@pytest.fixture(scope="module")
def serve(tmp_path_factory) -> Iterator[ServeProcess]:
    data = tmp_path_factory.mktemp("web-browser") / "data"
    users = UserStore.in_data_dir(data)
    for name, role in (("olga", "observer"), ("otto", "operator"), ("erin", "engineer")):
        users.add(name, role, PASSWORD)
    config = data.parent / "uacell.toml"
    config.write_text("[packml]\nacting_time = 0.5\nmach_speed = 120.0\n[robot]\ntime_scale = 4.0\n")
    sp = start_serve(data, "--config", str(config), web=True)
    sp.web = wait_for_web(sp)
    yield sp
    assert sp.stop() == 0


@pytest.fixture(scope="module")
def ua_thread() -> Iterator[UaThread]:
    t = UaThread()
    yield t
    t.close()


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser, serve):
    context = browser.new_context(viewport={"width": 1400, "height": 1000})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(serve.web)
    page.wait_for_selector("#conn[data-status=connected]", timeout=TIMEOUT)
    page.wait_for_selector('section.unit[data-unit="Filler1"] g.state.current', timeout=TIMEOUT)
    yield page
    context.close()
    assert not errors, errors


class Ua(CellClient):
    """An OPC UA client session of the tests (by NodeId: tests may, the HMI may not)."""

    def __init__(self, endpoint: str, user: str | None = None) -> None:
        super().__init__(endpoint, "urn:uacell:test:browser-peer", user, PASSWORD)

    async def state(self, machine: str) -> str | None:
        dv = await self.node(f"{machine}.CurrentState").read_data_value(raise_on_bad_status=False)
        return dv.Value.Value.Text if dv.StatusCode.is_good() and dv.Value and dv.Value.Value else None

    async def call(self, obj: str, method: str, *args: ua.Variant) -> ua.CallMethodResult:
        return await raw_call(self.client, ua.NodeId(obj, self.ns), ua.NodeId(f"{obj}.{method}", self.ns), *args)

    async def wait_state(self, machine: str, want: str, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while (state := await self.state(machine)) != want:
            assert time.monotonic() < deadline, f"{machine} stayed {state}, wanted {want}"
            await asyncio.sleep(0.05)

    async def filler_to_stopped(self) -> None:
        """Abort and Clear unless Filler1 already stands in Stopped."""
        if await self.state(MACHINE) == "Stopped":
            return
        if await self.state("Filler1.BaseStateMachine") == "Cleared":
            assert (await self.call("Filler1.BaseStateMachine", "Abort")).StatusCode.is_good()
        await self.wait_state("Filler1.BaseStateMachine", "Aborted")
        assert (await self.call("Filler1.BaseStateMachine", "Clear")).StatusCode.is_good()
        await self.wait_state(MACHINE, "Stopped")


def filler_stopped(serve: ServeProcess, ua_thread: UaThread) -> None:
    async def go() -> None:
        async with Ua(serve.endpoint) as c:
            await c.filler_to_stopped()

    ua_thread.run(go())


def current(page) -> str | None:
    return page.locator('section.unit[data-unit="Filler1"] g.state.current').first.get_attribute("data-state")


def shows_state(page, state: str, timeout: float = TIMEOUT) -> None:
    page.wait_for_selector(f'section.unit[data-unit="Filler1"] g.state.current[data-state="{state}"]', timeout=timeout)


def login(page, user: str) -> None:
    page.click("#login-open")
    page.fill("#login-user", user)
    page.fill("#login-password", PASSWORD)
    page.click("#login-submit")
    page.wait_for_function(f"() => document.querySelector('#who').textContent === '{user}'", timeout=TIMEOUT)
    # The user's own session has sent the page its snapshot (drawn anew): only now is what a test
    # types or clicks not redrawn away.
    page.wait_for_function(f"() => document.body.dataset.session === '{user}'", timeout=TIMEOUT)
    page.wait_for_selector("#conn[data-status=connected]", timeout=TIMEOUT)


def shot(target, name: str) -> None:
    target.screenshot(path=str(DOCS / name))


def unit_button(page, label: str):
    return page.locator(f'section.unit[data-unit="Filler1"] .commands button[data-label="{label}"]')


def robot_button(page, label: str, scope: str = ".controller"):
    return page.locator(f'{scope} > .commands button[data-label="{label}"]').first


def result(page, what: str, code: str) -> str:
    """The answer bar's text once it shows the answer to ``what`` (a button's label) with ``code``."""
    page.wait_for_function(
        """([what, code]) => { const r = document.querySelector('#result');
             const t = r.querySelector('.r-text');
             return r.dataset.code === code && t && t.textContent.startsWith(what + ': '); }""",
        arg=[what, code],
        timeout=TIMEOUT,
    )
    # The answer's time of day comes first, then what was done and how it went.
    assert re.fullmatch(r"\d{1,2}:\d{2}:\d{2}( [AP]M)?", page.inner_text("#result .r-time")), page.inner_text("#result")
    return page.inner_text("#result .r-text")


# --- the tests -----------------------------------------------------------------------------------


def test_the_page_shows_the_demo_cell(page, serve, ua_thread):
    filler_stopped(serve, ua_thread)
    shows_state(page, "Stopped")
    tree = page.inner_text("#tree")
    for part in ("Filler1", "Robot1", "Controller1", "TaskControl1", "Arm1"):
        assert part in tree
    assert page.locator("svg.tr88 g.state").count() == 17
    assert page.locator("svg.tr88 g.state.acting").count() == 10  # the acting states look different
    assert page.inner_text(".controller .v-sysop") == "Idle / StandBy"
    assert page.inner_text(".task .v-task") == "Idle"
    assert page.locator("table.axes tr").count() == 6
    files = page.locator(".file-list li").evaluate_all("items => items.map(i => i.dataset.file)")
    assert files == ["gripper.robot", "palletize.robot", "pick_and_place.robot"]
    # Deleting and uploading programs is for engineers: the server's UserExecutable says no.
    page.wait_for_function("() => document.querySelectorAll('.file-list button[data-method]').length === 3")
    assert all(b.is_disabled() for b in page.locator(".file-list button[data-method]").all())
    assert page.locator("button.upload").is_disabled()
    # Anonymous on loopback is an operator: Reset is offered in Stopped, Start is not.
    assert unit_button(page, "Reset").is_enabled() and not unit_button(page, "Start").is_enabled()
    shot(page, "web-overview.png")


RECORD = """() => {
  window.__seen = [];
  const note = () => {
    const g = document.querySelector('section.unit[data-unit="Filler1"] g.state.current');
    const s = g && g.dataset.state;
    if (s && window.__seen[window.__seen.length - 1] !== s) window.__seen.push(s);
  };
  note();
  // the page's main area, not the diagram: a new snapshot (an HMI reconnect) draws a new diagram
  const all = {subtree: true, attributes: true, childList: true};
  new MutationObserver(note).observe(document.querySelector('#cell'), all);
}"""


def test_reset_then_start_with_two_parameters(page, serve, ua_thread):
    filler_stopped(serve, ua_thread)
    shows_state(page, "Stopped")
    page.evaluate(RECORD)
    unit_button(page, "Reset").click()
    shows_state(page, "Idle")
    page.click('section.unit[data-unit="Filler1"] .params summary')
    for _ in range(2):
        page.click('section.unit[data-unit="Filler1"] .add-param')
    rows = page.locator('section.unit[data-unit="Filler1"] .param-rows tr')
    for i, (pid, name, unit, value) in enumerate([(1, "FillVolume", "ml", "250.5"), (2, "CapTorque", "Nm", "1.25")]):
        row = rows.nth(i)
        row.locator(".p-id").fill(str(pid))
        row.locator(".p-name").fill(name)
        row.locator(".p-unit").fill(unit)
        row.locator(".p-value").fill(value)
    unit_button(page, "Start").click()
    shows_state(page, "Execute")
    seen = page.evaluate("window.__seen")
    assert seen == ["Stopped", "Resetting", "Idle", "Starting", "Execute"], seen
    assert result(page, "Start", "Good") == "Start: done"
    processed = page.locator('section.unit[data-unit="Filler1"] .v-processed')
    page.wait_for_function("el => Number(el.textContent) > 0", arg=processed.element_handle(), timeout=TIMEOUT)
    first = int(processed.inner_text())
    page.wait_for_function(f"el => Number(el.textContent) > {first}", arg=processed.element_handle(), timeout=TIMEOUT)
    used = page.inner_text('section.unit[data-unit="Filler1"] .v-startparams')
    assert used == "FillVolume = 250.5 ml, CapTorque = 1.25 Nm"
    assert page.inner_text('section.unit[data-unit="Filler1"] .v-curmachspeed') == "120.0"

    async def arrived() -> list[Any]:
        async with Ua(serve.endpoint) as c:
            await c.client.load_data_type_definitions()
            return await c.node("Filler1.Status.StartParameters").read_value()

    params = ua_thread.run(arrived())
    assert [(p.ID, p.Name, p.Unit.DisplayName.Text, p.Value) for p in params] == [
        (1, "FillVolume", "ml", 250.5),
        (2, "CapTorque", "Nm", 1.25),
    ]
    shot(page.locator('section.unit[data-unit="Filler1"]'), "web-packml.png")


def test_an_opc_ua_clients_state_change_appears_within_a_second(page, serve, ua_thread):
    filler_stopped(serve, ua_thread)
    shows_state(page, "Stopped")

    async def reset() -> None:
        async with Ua(serve.endpoint, "otto") as c:
            assert (await c.call(MACHINE, "Reset")).StatusCode.is_good()

    ua_thread.run(reset())
    start = time.monotonic()
    page.wait_for_function(
        """() => ['Resetting', 'Idle'].includes(
             document.querySelector('section.unit[data-unit="Filler1"] g.state.current')?.dataset.state)""",
        timeout=1000,
    )
    assert time.monotonic() - start < 1.0
    shows_state(page, "Idle")
    entry = page.locator("#event-list li").first.inner_text()
    assert "Resetting → Idle" in entry or "Stopped → Running" in entry


def test_the_transition_list_names_the_user_who_caused_a_transition(page, serve, ua_thread):
    filler_stopped(serve, ua_thread)
    login(page, "otto")
    shows_state(page, "Stopped")
    unit_button(page, "Reset").click()
    shows_state(page, "Idle")
    # The server's AuditUpdateStateEvent names otto on the transition his Reset caused ...
    caused = page.locator('#event-list li[data-user="otto"]', has_text="Filler1/MachineState: Stopped → Running")
    caused.first.wait_for(timeout=TIMEOUT)
    assert caused.first.locator(".ev-user").inner_text() == "otto"
    # ... and on Resetting → Idle, which completed after his Reset returned (decision 38).
    completed = page.locator(
        '#event-list li[data-user="otto"]', has_text="Filler1/ExecuteState: Resetting → Idle"
    ).first
    completed.wait_for(timeout=TIMEOUT)
    assert completed.locator(".ev-user").inner_text() == "otto"
    shot(page.locator("#events"), "web-events.png")


def test_an_observer_sees_every_command_disabled_and_a_forced_call_refused(page, serve, ua_thread):
    filler_stopped(serve, ua_thread)
    login(page, "olga")
    shows_state(page, "Stopped")
    page.wait_for_function(
        "() => { const b = [...document.querySelectorAll('button[data-method]')];"
        " return b.length > 20 && b.every(x => x.disabled); }",
        timeout=TIMEOUT,
    )
    # Forced: the button made clickable in the page; the server refuses the observer's call.
    unit_button(page, "Reset").evaluate("b => { b.disabled = false; b.click(); }")
    text = result(page, "Reset", "BadUserAccessDenied")
    assert text == "Reset: your role may not do this (log in as a user who may) (BadUserAccessDenied)"

    async def state() -> str | None:
        async with Ua(serve.endpoint) as c:
            return await c.state(MACHINE)

    assert ua_thread.run(state()) == "Stopped"
    shot(page, "web-observer.png")


def test_a_lock_held_by_another_session_disables_the_robots_commands(page, serve, ua_thread):
    peer = Ua(serve.endpoint, "otto")
    ua_thread.run(peer.__aenter__())
    try:
        get_ready = robot_button(page, "Get ready")
        load = robot_button(page, "Load", ".task")
        page.wait_for_function("b => !b.disabled", arg=get_ready.element_handle(), timeout=TIMEOUT)
        res = ua_thread.run(peer.call(f"{CTRL}.Lock", "InitLock", ua.Variant("maintenance", ua.VariantType.String)))
        assert res.StatusCode.is_good() and res.OutputArguments[0].Value == 0
        page.wait_for_function("b => b.disabled", arg=get_ready.element_handle(), timeout=TIMEOUT)
        assert load.is_disabled() and robot_button(page, "Start", ".task").is_disabled()
        assert page.inner_text(".controller > .lock .v-lock") == "locked"
        assert "locked by otto" in page.inner_text(".task .lock-note")
        assert get_ready.get_attribute("title") == "Get ready: locked by otto"
        shot(page.locator("section.robot"), "web-lock.png")
        # Forced anyway: the server answers Bad_ResourceUnavailable.
        get_ready.evaluate("b => { b.disabled = false; b.click(); }")  # in one go: updates re-disable it
        assert result(page, "Get ready", "BadResourceUnavailable") == (
            "Get ready: another client holds the lock or the resource is busy (BadResourceUnavailable)"
        )

        async def sysop() -> str | None:
            async with Ua(serve.endpoint) as c:
                return await c.state(f"{CTRL}.SystemOperation.SystemOperationStateMachine")

        assert ua_thread.run(sysop()) == "Idle"
        res = ua_thread.run(peer.call(f"{CTRL}.Lock", "ExitLock"))
        assert res.StatusCode.is_good() and res.OutputArguments[0].Value == 0
        page.wait_for_function("b => !b.disabled", arg=get_ready.element_handle(), timeout=TIMEOUT)
        # The lock's own variables may arrive in a later notification than the buttons' state.
        page.wait_for_function(
            "() => document.querySelector('.controller > .lock .v-lock')?.textContent.trim() === 'free'",
            timeout=TIMEOUT,
        )
        assert page.inner_text(".controller > .lock .v-lock") == "free"
    finally:
        ua_thread.run(peer.__aexit__())


WAVE = (
    "# uploaded from the web HMI\nprogram Wave version 1.0\nspeed 100\n"
    "move 40 -20 10 0 30 0\nwait 8\nmove 0 0 0 0 0 0\n"
)


def test_what_the_user_is_typing_survives_a_new_snapshot(page, serve):
    login(page, "erin")
    page.click(".upload-box summary")
    page.fill(".upload-name", "draft.robot")
    page.fill(".upload-text", "program Draft\n")
    page.evaluate("render()")  # what a reconnect's new snapshot does
    assert page.eval_on_selector(".upload-box", "d => d.open") is True
    assert page.input_value(".upload-name") == "draft.robot"
    assert page.input_value(".upload-text") == "program Draft\n"


def test_a_program_uploaded_in_the_page_is_loaded_and_run(page, serve, ua_thread):
    login(page, "erin")
    page.click(".upload-box summary")
    page.fill(".upload-name", "wave.robot")
    page.fill(".upload-text", WAVE)
    page.click("button.upload")
    assert result(page, "Upload wave.robot", "Good") == "Upload wave.robot: done"
    page.wait_for_selector('.file-list li[data-file="wave.robot"]', timeout=TIMEOUT)
    (stored,) = (serve.data_dir / "programs").rglob("wave.robot")  # the controller's program directory
    assert stored.read_text() == WAVE
    page.select_option("select.program-select", "wave.robot")
    robot_button(page, "Load", ".task").click()
    page.wait_for_function(
        "() => document.querySelector('.task .v-task').textContent.startsWith('Ready')", timeout=TIMEOUT
    )
    assert page.inner_text(".task .v-program") == "Wave"
    robot_button(page, "Get ready").click()
    page.wait_for_function(
        "() => document.querySelector('.controller .v-sysop').textContent === 'Ready'", timeout=TIMEOUT
    )
    page.evaluate(
        """() => { window.__task = []; const el = document.querySelector('.task .v-task');
                   new MutationObserver(() => window.__task.push(el.textContent))
                     .observe(el, {childList: true, characterData: true, subtree: true}); }"""
    )
    start = robot_button(page, "Start", ".task")
    page.wait_for_function("b => !b.disabled", arg=start.element_handle(), timeout=TIMEOUT)
    start.click()
    page.wait_for_function("() => window.__task.includes('Executing')", timeout=TIMEOUT)
    page.wait_for_function(
        "() => Number(document.querySelector('tr[data-axis=Axis1] .pos').textContent) > 5", timeout=TIMEOUT
    )
    # The current line, as the server publishes it: the wait of 8 s (2 s at time_scale 4) is line 5.
    page.wait_for_function("() => document.querySelector('.task .v-line').textContent === 'line 5'", timeout=TIMEOUT)
    assert page.locator(".task .v-line").is_visible()
    shot(page.locator("section.robot"), "web-robot.png")
    page.wait_for_function(
        "() => document.querySelector('.task .v-task').textContent === 'Ready / AtProgramStart'", timeout=TIMEOUT
    )
    page.wait_for_function("() => document.querySelector('.task .v-line').hidden", timeout=TIMEOUT)  # line 0
    assert re.search(r"TaskControl1: Executing → Ready", page.inner_text("#event-list"))
    robot_button(page, "Stand down").click()
    page.wait_for_function(
        "() => document.querySelector('.controller .v-sysop').textContent.startsWith('Idle')", timeout=TIMEOUT
    )


def test_an_expired_session_goes_back_to_login(page, serve):
    page.context.clear_cookies()
    page.click('section.unit[data-unit="Filler1"] button[data-label="Set speed"]')
    page.wait_for_selector("#login[open]", timeout=TIMEOUT)
    assert "expired" in page.inner_text("#login-why")
    page.fill("#login-user", "otto")
    shot(page, "web-login.png")
    page.fill("#login-password", PASSWORD)
    page.click("#login-submit")
    page.wait_for_function("() => document.querySelector('#who').textContent === 'otto'", timeout=TIMEOUT)


def test_an_alarm_is_shown_and_acknowledged_in_the_page(page, serve, ua_thread):
    login(page, "erin")
    row = page.locator('.condition[data-condition="EmergencyStop"]')
    page.click('button[data-label="Simulate emergency stop"]')
    page.wait_for_selector('.condition[data-condition="EmergencyStop"][data-active="true"]', timeout=TIMEOUT)
    assert row.locator(".c-state").inner_text() == "ACTIVE"
    # The server: GetReady is not Executable while an alarm is active.
    page.wait_for_function("b => b.disabled", arg=robot_button(page, "Get ready").element_handle(), timeout=TIMEOUT)
    page.click('button[data-label="Release emergency stop"]')
    page.wait_for_function(
        "el => el.textContent === 'inactive, not acknowledged'",
        arg=row.locator(".c-state").element_handle(),
        timeout=TIMEOUT,
    )
    ack = row.locator('button[data-label="Acknowledge"]')
    page.wait_for_function("b => !b.disabled", arg=ack.element_handle(), timeout=TIMEOUT)
    ack.click()
    assert result(page, "Acknowledge", "Good") == "Acknowledge: done"
    page.wait_for_function(
        "el => el.textContent === 'ok'", arg=row.locator(".c-state").element_handle(), timeout=TIMEOUT
    )

    async def acked() -> tuple[bool, str]:
        async with Ua(serve.endpoint) as c:
            cond = f"{CTRL}.SystemOperation.Conditions.EmergencyStop"
            return (
                await c.node(f"{cond}.AckedState.Id").read_value(),
                (await c.node(f"{cond}.Comment").read_value()).Text,
            )

    assert ua_thread.run(acked()) == (True, "acknowledged in the web HMI")


def test_the_page_says_when_the_server_is_unreachable_and_comes_back(browser, ua_thread, tmp_path):
    from conftest import fast_config, start_app

    from uacell.security.pki import PkiPaths
    from uacell.web.hosting import start_web, trust_hmi

    data = tmp_path / "data"
    config = fast_config(data)
    app = ua_thread.run(start_app(config))
    trust_hmi(data)
    web = ua_thread.run(
        start_web(
            app.endpoint, data, companions=app.companions, port=0, server_certificate=PkiPaths.in_data_dir(data).cert
        )
    )
    context = browser.new_context(viewport={"width": 1400, "height": 1000})
    try:
        page = context.new_page()
        page.goto(web.url)
        page.wait_for_selector("#conn[data-status=connected]", timeout=TIMEOUT)
        ua_thread.run(app.stop())
        page.wait_for_selector("#conn[data-status=unreachable]", timeout=TIMEOUT)
        assert page.inner_text("#conn") == "server unreachable"
        notice = page.inner_text("#notice")
        assert f"the OPC UA server {app.endpoint} cannot be reached" in notice and "Reconnecting" in notice
        assert all(b.is_disabled() for b in page.locator("button[data-method]").all())
        app = ua_thread.run(start_app(config))  # the same port and data directory
        page.wait_for_selector("#conn[data-status=connected]", timeout=60_000)
        assert page.locator("#notice").is_hidden()
        page.fill('section.unit[data-unit="Filler1"] .speed-input', "42")
        page.click('section.unit[data-unit="Filler1"] button[data-label="Set speed"]')
        assert result(page, "Set speed", "Good") == "Set speed: done"
        page.wait_for_function(
            """() => document.querySelector('section.unit[data-unit="Filler1"] .v-machspeed').textContent === '42.0'""",
            timeout=TIMEOUT,
        )
    finally:
        context.close()
        ua_thread.run(web.stop())
        ua_thread.run(app.stop())


# --- an operator's shift ----------------------------------------------------------------------------


def test_disabled_commands_say_why_on_hover_and_in_the_page(page, serve, ua_thread):
    filler_stopped(serve, ua_thread)
    shows_state(page, "Stopped")
    login(page, "otto")
    page.wait_for_function("() => document.querySelector('#role').textContent === 'operator'", timeout=TIMEOUT)
    assert page.locator("#role").is_visible()  # the role beside the user, as the server says it
    start = unit_button(page, "Start")
    page.wait_for_function("b => b.disabled && b.dataset.why", arg=start.element_handle(), timeout=TIMEOUT)
    assert start.get_attribute("title") == "Start: not possible in state Stopped"
    why = page.locator('section.unit[data-unit="Filler1"] .commands + .why-line').first
    assert "Start: not possible in state Stopped" in why.inner_text()
    assert "Reset:" not in why.inner_text()  # Reset can be used: it is not listed
    # An observer: the role is the reason.
    page.click("#logout")
    login(page, "olga")
    page.wait_for_function("() => document.querySelector('#role').textContent === 'observer'", timeout=TIMEOUT)
    reset = unit_button(page, "Reset")
    page.wait_for_function(
        "b => b.title === 'Reset: your role may not do this (olga)'", arg=reset.element_handle(), timeout=TIMEOUT
    )
    assert "Reset: your role may not do this (olga)" in why.inner_text()


def test_a_speed_out_of_range_is_refused_in_plain_words_with_its_code(page, serve, ua_thread):
    login(page, "otto")
    speed = page.locator('section.unit[data-unit="Filler1"] .speed-input')
    label = page.locator(f'label[for="{speed.get_attribute("id")}"]')
    assert label.inner_text() == "Speed (MachSpeed)"  # a visible label, and the unit beside the field
    assert page.locator('section.unit[data-unit="Filler1"] .unit-text').inner_text() == "packages/min"
    unit_button_speed = page.locator('section.unit[data-unit="Filler1"] button[data-label="Set speed"]')
    page.wait_for_selector('section.unit[data-unit="Filler1"] button[data-label="Set speed"]:enabled', timeout=TIMEOUT)
    speed.fill("5000")
    assert speed.input_value() == "5000"
    unit_button_speed.click()
    text = result(page, "Set speed", "BadInvalidArgument")
    assert text == "Set speed: speed must be within 0..600 packages/min (BadInvalidArgument)"

    async def mach_speed() -> float:
        async with Ua(serve.endpoint) as c:
            return float(await c.node("Filler1.Status.MachSpeed").read_value())

    assert ua_thread.run(mach_speed()) <= 600  # nothing changed


def test_abort_asks_first_and_does_nothing_when_declined(page, serve, ua_thread):
    filler_stopped(serve, ua_thread)
    shows_state(page, "Stopped")
    login(page, "otto")
    asked: list[str] = []

    def decline(dialog) -> None:
        asked.append(dialog.message)
        dialog.dismiss()

    page.on("dialog", decline)
    abort = unit_button(page, "Abort")
    page.wait_for_function("b => !b.disabled", arg=abort.element_handle(), timeout=TIMEOUT)
    abort.click()
    page.wait_for_function("() => true")  # the dialog ran synchronously inside the click
    assert asked == ["Abort Filler1? It stops at once, mid-cycle."]

    async def state() -> str | None:
        async with Ua(serve.endpoint) as c:
            return await c.state(MACHINE)

    assert ua_thread.run(state()) == "Stopped"  # declined: no call was made
    page.remove_listener("dialog", decline)
    page.once("dialog", lambda dialog: dialog.accept())
    abort.click()
    result(page, "Abort", "Good")
    shows_state(page, "Aborted")


def test_an_active_alarm_shows_a_banner_over_the_page(page, serve, ua_thread):
    login(page, "erin")
    banner = page.locator("#alarm")
    assert banner.is_hidden()
    page.click('button[data-label="Simulate emergency stop"]')
    page.wait_for_function("() => !document.querySelector('#alarm').hidden", timeout=TIMEOUT)
    assert banner.inner_text().startswith("Alarm — Robot1/Controller1: EmergencyStop active")
    page.click('button[data-label="Release emergency stop"]')
    page.wait_for_function(
        "() => document.querySelector('#alarm').textContent.includes('EmergencyStop to acknowledge')",
        timeout=TIMEOUT,
    )
    row = page.locator('.condition[data-condition="EmergencyStop"]')
    ack = row.locator('button[data-label="Acknowledge"]')
    page.wait_for_function("b => !b.disabled", arg=ack.element_handle(), timeout=TIMEOUT)
    ack.click()
    page.wait_for_function("() => document.querySelector('#alarm').hidden", timeout=TIMEOUT)


def test_a_sample_program_runs_by_following_the_page(page, serve, ua_thread):
    """The hint's steps with the shipped pick_and_place, which uses the module gripper: Start says why
    it waits, the Modules line shows the module once loaded, then the program runs."""
    login(page, "otto")
    hint = page.locator(".controller .hint").inner_text()
    assert "pick_and_place and palletize use gripper" in hint
    robot_button(page, "Get ready").click()
    page.wait_for_function(
        "() => document.querySelector('.controller .v-sysop').textContent === 'Ready'", timeout=TIMEOUT
    )
    page.select_option("select.program-select", "pick_and_place.robot")
    robot_button(page, "Load", ".task").click()
    # An earlier test of this module may have left its own program loaded (Ready already): wait for
    # this one's name, then for Start to say why it waits (a moment earlier it may still show the
    # previous program's answer).
    page.wait_for_function(
        "() => document.querySelector('.task .v-task').textContent.startsWith('Ready')"
        " && document.querySelector('.task .v-program').textContent === 'PickAndPlace'",
        timeout=TIMEOUT,
    )
    start = robot_button(page, "Start", ".task")
    why = "Start: the program uses a module that is not loaded: load it first (see the hint above)"
    page.wait_for_function(
        "([b, why]) => b.disabled && b.title === why", arg=[start.element_handle(), why], timeout=TIMEOUT
    )
    assert start.is_disabled() and start.get_attribute("title") == why
    assert page.inner_text(".task .v-modules") == "none"
    page.select_option("select.program-select", "gripper.robot")
    robot_button(page, "Load", ".task").click()
    # The Modules line follows the load (no state or program name changed).
    page.wait_for_function(
        "() => document.querySelector('.task .v-modules').textContent === 'Gripper'", timeout=TIMEOUT
    )
    page.wait_for_function("b => !b.disabled", arg=start.element_handle(), timeout=TIMEOUT)
    start.click()
    page.wait_for_function(
        "() => document.querySelector('.task .v-task').textContent.startsWith('Executing')", timeout=TIMEOUT
    )
    robot_button(page, "Stop", ".task").click()
    page.wait_for_function(
        "() => document.querySelector('.task .v-task').textContent.startsWith('Ready')", timeout=TIMEOUT
    )
    robot_button(page, "Unload", ".task").click()
    page.wait_for_function("() => document.querySelector('.task .v-modules').textContent === 'none'", timeout=TIMEOUT)
    robot_button(page, "Stand down").click()
    page.wait_for_function(
        "() => document.querySelector('.controller .v-sysop').textContent.startsWith('Idle')", timeout=TIMEOUT
    )


def test_an_observer_cannot_view_program_files_and_is_told_why(page, serve):
    login(page, "olga")
    # The list is drawn again whenever it changes: wait on what the page shows, not on one element.
    page.wait_for_selector(
        '.file-list li[data-file="pick_and_place.robot"] button:disabled:text("View")', timeout=TIMEOUT
    )
    view = page.locator('.file-list li[data-file="pick_and_place.robot"] button:text("View")')
    assert view.get_attribute("title") == "View: your role may not read program files (olga)"
    page.click("#logout")
    login(page, "otto")  # an operator may read them
    page.wait_for_selector(
        '.file-list li[data-file="pick_and_place.robot"] button:enabled:text("View")', timeout=TIMEOUT
    )
    view.click()
    page.wait_for_function("() => document.querySelector('#viewer').open", timeout=TIMEOUT)
    assert "program PickAndPlace" in page.inner_text("#viewer-text")


def _open(browser, serve, width: int, height: int):
    context = browser.new_context(viewport={"width": width, "height": height})
    page = context.new_page()
    page.goto(serve.web)
    page.wait_for_selector("#conn[data-status=connected]", timeout=TIMEOUT)
    page.wait_for_selector(
        'section.unit[data-unit="Filler1"] .state-list li.current', state="attached", timeout=TIMEOUT
    )
    return context, page


def test_the_state_diagram_reads_at_1280x800_and_becomes_a_list_on_a_phone(browser, serve):
    context, page = _open(browser, serve, 1280, 800)
    try:
        geometry = page.evaluate(
            """() => {
              const svg = document.querySelector('svg.tr88[data-unit="Filler1"]');
              const scale = svg.getBoundingClientRect().width / svg.viewBox.baseVal.width;
              const r = (e) => { const b = e.getBoundingClientRect(); return [b.left, b.top, b.right, b.bottom]; };
              const ends = [...svg.querySelectorAll('polyline.edge')].map((p) => {
                const pts = p.getAttribute('points').trim().split(' '); return pts[pts.length - 1]; });
              return {
                font: parseFloat(getComputedStyle(svg.querySelector(".edge-label")).fontSize) * scale,
                labels: [...svg.querySelectorAll('.edge-label')].map((t) => [t.textContent, r(t)]),
                boxes: [...svg.querySelectorAll('g.state rect')].map(r),
                ends,
              };
            }"""
        )
        assert geometry["font"] >= 11, geometry["font"]  # edge labels at least 11 px on screen

        def overlaps(a, b) -> bool:
            return a[0] < b[2] - 1 and b[0] < a[2] - 1 and a[1] < b[3] - 1 and b[1] < a[3] - 1

        for text, label in geometry["labels"]:
            assert not any(overlaps(label, box) for box in geometry["boxes"]), f"{text} is cut by a state box"
        assert len(set(geometry["ends"])) == len(geometry["ends"])  # every arrow has its own arrowhead
        shot(page.locator('section.unit[data-unit="Filler1"]'), "web-packml-1280.png")
    finally:
        context.close()
    context, page = _open(browser, serve, 390, 844)
    try:
        assert not page.locator('svg.tr88[data-unit="Filler1"]').is_visible()
        states = page.locator('section.unit[data-unit="Filler1"] .state-list')
        assert states.is_visible()
        current = states.locator("li.current")
        assert current.count() == 1 and current.get_attribute("aria-current") == "step"
        assert current.inner_text() == page.inner_text('section.unit[data-unit="Filler1"] .v-state')
        shot(page, "web-phone.png")
    finally:
        context.close()
