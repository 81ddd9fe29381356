"""The HMI's machine overview in a real headless browser (Debian's Chromium driven by Playwright): one
tile per OPC 40001-1 machine with its MachineryItemState and MachineryOperationMode, following the
cell live. Uses the fixtures of test_web_browser (one `uacell serve` with the HMI for the module)."""

from __future__ import annotations

from asyncua import ua
from test_web_browser import (  # noqa: F401 (fixtures)
    MACHINE,
    TIMEOUT,
    Ua,
    browser,
    filler_stopped,
    page,
    pytestmark,
    serve,
    ua_thread,
)

EXEC = f"{MACHINE}.ExecuteState"


def tile(view, name: str):
    return view.locator(f'#machines .machine-tile[data-machine="{name}"]')


def test_one_tile_per_machine_follows_its_state_and_mode(page, serve, ua_thread):  # noqa: F811 (fixtures)
    filler_stopped(serve, ua_thread)
    assert page.locator("#machines h2").text_content() == "Machines"
    assert page.locator("#machines .machine-tile").count() == 2
    page.wait_for_selector(
        '#machines .machine-tile[data-machine="Filler1"][data-state="NotExecuting"]', timeout=TIMEOUT
    )
    assert tile(page, "Filler1").locator(".m-mode").text_content() == "Processing"
    robot = tile(page, "Robot1")
    assert robot.locator(".m-state").text_content() == "NotExecuting"
    assert "DEMO-R1" in robot.locator(".m-ident").text_content()  # the robot's serial number

    async def start() -> None:
        async with Ua(serve.endpoint) as c:
            assert (await c.call(MACHINE, "Reset")).StatusCode.is_good()
            await c.wait_state(EXEC, "Idle")
            empty = ua.Variant([], ua.VariantType.ExtensionObject, is_array=True)
            assert (await c.call(EXEC, "Start", empty)).StatusCode.is_good()

    ua_thread.run(start())
    page.wait_for_selector('#machines .machine-tile[data-machine="Filler1"][data-state="Executing"]', timeout=TIMEOUT)
    filler_stopped(serve, ua_thread)  # Abort, Clear: through OutOfService back to NotExecuting
    page.wait_for_selector(
        '#machines .machine-tile[data-machine="Filler1"][data-state="NotExecuting"]', timeout=TIMEOUT
    )
