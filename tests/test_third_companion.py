"""A third companion defined only in the tests (tests/companions/testco): added to the companions a
server and its HMI are built with, it appears in the address space, the HMI (its own browser module,
in a real Chromium), history, PubSub (on Debian's mosquitto), the NodeSet export and /metrics, while
nothing outside tests/ names it. One server with the HMI beside it for the module, driven from a
thread's event loop (the browser tests are synchronous)."""

from __future__ import annotations

import urllib.error
import urllib.request
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from companions.testco.companion import FOLDER, START_TEMPERATURE, TESTCO, temperature_node
from conftest import ROOT, fast_config, start_app
from helpers import free_port, until, wait_until
from mqtt_broker import MOSQUITTO, Broker, subscribed
from test_history_server import history, raw
from test_operations import sample, scrape
from test_web_browser import ARGS, CHROMIUM, TIMEOUT, UaThread

from uacell.catalog import companions
from uacell.cli.nodeset_export import export_cell
from uacell.core.companion import web_views
from uacell.security.pki import PkiPaths
from uacell.web.discovery import discover
from uacell.web.hosting import start_web, trust_hmi

UNIT = "Filler1"
FIELD = "Thermometer/Temperature"
WITH_TESTCO = (*companions(), TESTCO)


class Rig:
    def __init__(self, app: Any, web: Any, sub: Any, started: datetime) -> None:
        self.app, self.web, self.sub, self.started = app, web, sub, started

    @property
    def ns(self) -> int:
        return self.app.cell.instantiator.ns

    async def kept(self, value: float) -> None:
        """Wait until history holds ``value`` (the batched writer stores it soon after)."""
        async with Client(self.app.endpoint, timeout=30) as client:
            node = temperature_node(UNIT, self.ns)

            async def values() -> bool:
                (res,) = await history(client, raw(datetime.now(UTC) - timedelta(hours=1), datetime.now(UTC)), node)
                return value in [dv.Value.Value for dv in res.HistoryData.DataValues or []]

            await until(values, True)

    async def set_temperature(self, value: float) -> None:
        """The equipment's new temperature, as a binder would publish it (a server-side write)."""
        node = temperature_node(UNIT, self.ns)
        await self.app.space.write(node, ua.AttributeIds.Value, ua.Variant(value, ua.VariantType.Double))


@pytest.fixture(scope="module")
def ua_thread() -> Iterator[UaThread]:
    t = UaThread()
    yield t
    t.close()


@pytest.fixture(scope="module")
def rig(tmp_path_factory, ua_thread) -> Iterator[Rig]:
    data = tmp_path_factory.mktemp("testco") / "data"
    started = datetime.now(UTC) - timedelta(seconds=1)
    config = fast_config(data)
    config.metrics.enabled, config.metrics.port = True, free_port()
    broker = None
    if MOSQUITTO is not None:
        broker = Broker(data.parent / "broker")
        broker.start()
        p = config.pubsub
        p.enabled, p.broker, p.publisher_id, p.publishing_interval = True, broker.url, "cell-under-test", 0.05
    sub_cm = subscribed(broker, "opcua/#") if broker is not None else None
    sub = ua_thread.run(sub_cm.__aenter__()) if sub_cm is not None else None
    app = ua_thread.run(start_app(config, companions=WITH_TESTCO))
    trust_hmi(data)
    web = None
    try:
        web = ua_thread.run(
            start_web(
                app.endpoint, data, port=0, server_certificate=PkiPaths.in_data_dir(data).cert, companions=WITH_TESTCO
            )
        )
        yield Rig(app, web, sub, started)
    finally:
        if web is not None:
            ua_thread.run(web.stop())
        ua_thread.run(app.stop())
        if sub_cm is not None:
            ua_thread.run(sub_cm.__aexit__(None, None, None))
        if broker is not None:
            broker.stop()


def test_nothing_outside_the_tests_names_the_third_companion() -> None:
    named = [
        p for p in (ROOT / "src").rglob("*") if p.is_file() and p.suffix in (".py", ".js", ".css", ".html", ".toml")
    ]
    assert named and not [p for p in named if b"testco" in p.read_bytes().lower() or b"Thermometer" in p.read_bytes()]
    assert TESTCO not in companions()


def test_it_appears_in_the_address_space(rig: Rig, ua_thread: UaThread) -> None:
    async def browse() -> tuple[list[str], float, Any]:
        async with Client(rig.app.endpoint, timeout=30) as client:
            objects = client.nodes.objects
            folder = await objects.get_child(f"{rig.ns}:{FOLDER}")
            organized = [(await n.read_browse_name()).Name for n in await folder.get_children(ua.ObjectIds.Organizes)]
            variable = client.get_node(temperature_node(UNIT, rig.ns))
            value = await variable.read_value()
            dtype = await variable.read_data_type()
            return organized, value, dtype

    organized, value, dtype = ua_thread.run(browse())
    assert organized == [UNIT]
    assert value == START_TEMPERATURE and dtype == ua.NodeId(ua.ObjectIds.Double)


def test_history_keeps_its_declared_values(rig: Rig, ua_thread: UaThread) -> None:
    started = rig.started  # before the server: its first value is kept from its start

    async def run() -> None:
        async with Client(rig.app.endpoint, timeout=30) as client:
            node = temperature_node(UNIT, rig.ns)
            historizing = await client.get_node(node).read_attribute(ua.AttributeIds.Historizing)
            assert historizing.Value.Value is True
            await rig.set_temperature(24.25)

            async def kept() -> list[float]:  # the batched writer stores it soon after
                (res,) = await history(client, raw(started, datetime.now(UTC) + timedelta(seconds=5)), node)
                return [dv.Value.Value for dv in res.HistoryData.DataValues]

            await until(kept, [START_TEMPERATURE, 24.25])

    ua_thread.run(run())


def test_pubsub_publishes_its_dataset(rig: Rig, ua_thread: UaThread) -> None:
    if rig.sub is None:
        pytest.skip("Debian's mosquitto is not installed (make mosquitto)")

    async def run() -> None:
        meta = await rig.sub.wait_for(lambda r: r.topic.endswith(f"/metadata/cell-under-test/Cell/{UNIT}"))
        fields = {f["Name"]: f for f in meta.body["MetaData"]["Fields"]}
        assert fields[FIELD]["BuiltInType"] == 11  # Double
        await rig.set_temperature(26.5)

        def published() -> list[Any]:
            return [m["Payload"][FIELD]["Value"] for m in rig.sub.data(f"/{UNIT}") if FIELD in m.get("Payload", {})]

        await wait_until(lambda: 26.5 in published())

    ua_thread.run(run())


def test_metrics_carry_its_figures(rig: Rig, ua_thread: UaThread) -> None:
    ua_thread.run(rig.set_temperature(19.0))
    status, body = ua_thread.run(scrape(rig.app))
    assert status.endswith("200 OK")
    assert sample(body, "testco_thermometers") == 1.0
    assert sample(body, "testco_temperature", unit=UNIT) == 19.0


def test_the_nodeset_export_holds_its_nodes(tmp_path: Path, ua_thread: UaThread) -> None:
    def exported(found: tuple[Any, ...]) -> set[str]:
        root = ET.fromstring(ua_thread.run(export_cell(fast_config(tmp_path / "export"), found)))
        return {node_id for e in root if (node_id := e.get("NodeId"))}

    with_it = exported(WITH_TESTCO)
    assert {f"ns=1;s={UNIT}.Thermometer", f"ns=1;s={UNIT}.Thermometer.Temperature"} <= with_it
    assert not {n for n in exported(companions()) if "Thermometer" in n}


def test_the_hmi_discovers_it_and_serves_its_view(rig: Rig, ua_thread: UaThread) -> None:
    async def found() -> Any:
        async with Client(rig.app.endpoint, timeout=30) as client:
            return await discover(client, web_views(WITH_TESTCO))

    cell = ua_thread.run(found())
    (part,) = cell.layout["thermometers"]
    assert part == {"name": UNIT, "temperature": f"{FOLDER}/{UNIT}/Temperature"}
    assert cell.variables[part["temperature"]] == temperature_node(UNIT, rig.ns)
    with urllib.request.urlopen(rig.web.url, timeout=30) as answer:
        page = answer.read().decode()
    assert '<script type="module" src="/views/thermometers.js"></script>' in page
    with urllib.request.urlopen(f"{rig.web.url}views/thermometers.js", timeout=30) as answer:
        script = answer.read()
        assert answer.headers["Content-Type"] == "text/javascript; charset=utf-8"
    assert script == (ROOT / "tests/companions/testco/static/view.js").read_bytes()
    for undeclared in ("nothing.js", "thermometers.py", "..%2Fcompanion.py"):  # only the declared files
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(f"{rig.web.url}views/{undeclared}", timeout=30)
        refused.value.close()
        assert refused.value.code == 404


@pytest.mark.skipif(
    not Path(CHROMIUM).exists(), reason="Chromium is not installed (make setup installs it where it can)"
)
def test_the_page_draws_it_with_its_own_module_and_history(rig: Rig, ua_thread: UaThread) -> None:
    from playwright.sync_api import sync_playwright

    ua_thread.run(rig.set_temperature(22.0))
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            page = browser.new_context(viewport={"width": 1400, "height": 1000}).new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(rig.web.url)
            page.wait_for_selector("#conn[data-status=connected]", timeout=TIMEOUT)
            card = f'section.thermometer[data-thermometer="{UNIT}"]'
            page.wait_for_function(
                f"() => document.querySelector('{card} .t-value')?.textContent === '22.0'", timeout=TIMEOUT
            )
            # its stylesheet, served from its package, applies
            color = page.eval_on_selector(f"{card} .t-value", "e => getComputedStyle(e).color")
            assert color == "rgb(200, 40, 40)"
            assert page.locator(f'#tree a[href="#thermometer-{UNIT}"]').text_content() == f"{UNIT} (thermometer)"
            # the other companions' parts are there as before
            assert page.locator(f'section.unit[data-unit="{UNIT}"]').count() == 1
            assert page.locator(".machine-tile").count() == 2
            ua_thread.run(rig.set_temperature(23.5))  # live
            page.wait_for_function(
                f"() => document.querySelector('{card} .t-value').textContent === '23.5'", timeout=TIMEOUT
            )
            ua_thread.run(rig.kept(23.5))
            page.click("#history-refresh")
            history_text = f'#history-body article.hist-thermometer[data-thermometer="{UNIT}"] .t-history'
            page.wait_for_function(
                f"() => (document.querySelector('{history_text}')?.textContent || '').split(' ').includes('23.5')",
                timeout=TIMEOUT,
            )
            assert not errors, errors
        finally:
            browser.close()
