"""The one door to asyncua (uacell.ua.door): nothing outside it touches asyncua's private names or
replaces an asyncua attribute, its inventory is what a started server installed and what the
installed asyncua still has, and a different asyncua is refused at attach (docs/asyncua.md)."""

from __future__ import annotations

import importlib
import inspect
import logging
import re
import textwrap
from pathlib import Path
from typing import Any

import pytest
from asyncua_touches import touches
from conftest import fast_config, start_app

from uacell.ua import door
from uacell.ua.door import ENTRIES, INVENTORY, DoorError, Kind
from uacell.ua.door.processing import attach

SRC = Path(__file__).resolve().parents[1] / "src" / "uacell"
DOOR = SRC / "ua" / "door"


def test_no_module_outside_the_door_touches_asyncua_past_its_public_surface() -> None:
    found: list[str] = []
    for path in sorted(SRC.rglob("*.py")):
        if DOOR in path.parents:
            continue
        module = str(path.relative_to(SRC.parent))
        found.extend(str(t) for t in touches(path.read_text(encoding="utf-8"), module))
    assert found == [], "go through uacell.ua.door (and list it in its inventory):\n" + "\n".join(found)


OFFENDING = textwrap.dedent(
    """\
    from asyncua import Server, ua
    from asyncua.server.address_space import AddressSpace, MethodService
    from asyncua.server.uaprocessor import UaProcessor
    from asyncua.common.utils import _private_helper
    import asyncua.server._internal


    def nodes(server: Server) -> object:
        return server.iserver.aspace._nodes


    def swap(server: Server) -> None:
        server.iserver.method_service = object()


    def patch() -> None:
        UaProcessor.process = None
        setattr(UaProcessor, "open_secure_channel", None)


    def sneak(processor: UaProcessor) -> object:
        return getattr(processor, "_connection", None)


    def local(aspace: AddressSpace) -> None:
        table = aspace
        table._nodes = {}


    class Dispatcher(MethodService):
        async def call(self, request):
            return await super()._call(request)

        def space(self):
            return self._aspace
    """
)


def test_the_checker_names_the_line_of_each_touch_in_an_offending_module() -> None:
    found = {(t.line, t.what.split(" ")[0]) for t in touches(OFFENDING, "snippet.py")}
    lines = OFFENDING.splitlines()

    def line(text: str) -> int:
        return next(n for n, source in enumerate(lines, 1) if text in source)

    assert (line("import _private_helper"), "imports") in found
    assert (line("import asyncua.server._internal"), "imports") in found
    assert (line("aspace._nodes\n".strip()), "reaches") in found
    assert (line("method_service = object()"), "assigns") in found
    assert (line("UaProcessor.process = None"), "assigns") in found
    assert (line('setattr(UaProcessor, "open_secure_channel"'), "setattr") in found
    assert (line('getattr(processor, "_connection"'), "getattr") in found
    assert (line("table._nodes = {}"), "assigns") in found
    assert (line("class Dispatcher(MethodService)"), "class") in found
    assert (line("super()._call(request)"), "reaches") in found
    assert (line("return self._aspace"), "reaches") in found
    assert all(str(t).startswith("snippet.py:") for t in touches(OFFENDING, "snippet.py"))


FINE = textwrap.dedent(
    """\
    from asyncua import Client, Server, ua
    from asyncua.server.address_space import MethodService
    from uacell.ua import door


    class Mine:
        def __init__(self) -> None:
            self._locks = {}
            self._aspace = None

        def read(self) -> object:
            return self._locks, self._aspace, _helper()


    def _helper() -> int:
        return 1


    def fill(server: Server) -> ua.CallMethodResult:
        result = ua.CallMethodResult()
        result.StatusCode = ua.StatusCode(0)
        client = Client("opc.tcp://127.0.0.1:4840")
        client.application_uri = "urn:test"
        return result


    @door.subclass("asyncua.server.address_space.MethodService")
    class Dispatcher(MethodService):
        def __init__(self, aspace) -> None:
            super().__init__(aspace)
            self._mine = 1
            self.aspace = aspace

        def space(self):
            return self.aspace, self._mine
    """
)


def test_the_checker_leaves_uacells_own_privates_values_and_registered_subclasses_alone() -> None:
    assert touches(FINE, "fine.py") == []


def _defines(target: str) -> bool:
    """Does the installed package still have ``target`` (a module, class or module attribute, a class
    attribute, or an attribute its class (or a base) sets in its source)?"""
    path, _, name = target.rpartition(".")
    parts = path.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            owner: Any = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for part in parts[cut:]:
            owner = getattr(owner, part, None)
        break
    if owner is None:
        return False
    if hasattr(owner, name) or (inspect.ismodule(owner) and owner.__name__ == "dataclasses" and name == "exec"):
        return True
    classes = inspect.getmro(owner) if inspect.isclass(owner) else ()
    pattern = re.compile(rf"self\.{re.escape(name)}\s*[:=]")
    return any(pattern.search(inspect.getsource(c)) for c in classes if c is not object and c.__module__ != "builtins")


@pytest.mark.parametrize("entry", ENTRIES, ids=lambda e: e.target)
def test_every_inventory_entry_names_something_the_installed_package_has(entry: door.Entry) -> None:
    assert _defines(entry.target), f"{entry.target} is gone: re-read it (docs/asyncua.md, how to upgrade)"


async def test_the_inventory_is_what_a_started_server_installed(tmp_path: Path) -> None:
    app = await start_app(fast_config(tmp_path / "data"))
    try:
        installed = door.installed()
        changes = {e.target for e in ENTRIES if e.kind is not Kind.PRIVATE}
        at_start = {e.target for e in ENTRIES if e.kind is not Kind.PRIVATE and e.at_start}
        assert installed <= changes  # nothing installed that the inventory does not list
        assert at_start - installed == set()  # everything a start installs, installed
        from asyncua.server.uaprocessor import UaProcessor

        from uacell.ua.door import processing

        assert UaProcessor.process is processing._process  # patched, as listed
        assert app.server.iserver.method_service is app.dispatcher
    finally:
        await app.stop()


async def test_a_stop_cancels_asyncuas_clock_instead_of_waiting_for_it(tmp_path: Path) -> None:
    """asyncua's stop waits for its clock loop to wake from its one-second sleep; uacell's cancels it
    (a stop of the served demo cell then takes milliseconds, not up to a second)."""
    app = await start_app(fast_config(tmp_path / "data"))
    clock = app.server.iserver.time_task
    assert clock is not None and not clock.done()
    await app.stop()
    assert clock.cancelled()  # asyncua's own stop lets it finish its sleep and end normally
    assert "asyncua.server.internal_server.InternalServer.time_task" in door.installed()


def test_a_change_not_in_the_inventory_is_refused() -> None:
    class Thing:
        attribute = 1

    with pytest.raises(DoorError, match=r"not in uacell\.ua\.door\.inventory"):
        door.swap(Thing(), "Thing.attribute", 2)
    with pytest.raises(DoorError, match="listed as a subclass"):
        door.swap(Thing(), "asyncua.server.address_space.MethodService", 2)
    assert Thing.attribute == 1


def test_a_different_asyncua_is_refused_at_attach_in_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(door.VERIFIED, "asyncua", "0.0.1")
    with pytest.raises(DoorError) as refused:
        door.check_versions()
    message = str(refused.value)
    assert "\n" not in message and "0.0.1" in message and "asyncua 2.1.0 is installed" in message
    assert "docs/asyncua.md" in message


def test_a_different_uvicorn_is_a_warning(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    import uvicorn  # checked once loaded (the web HMI loads it before the server attaches)

    assert uvicorn.__version__
    monkeypatch.setitem(door.VERIFIED, "uvicorn", "0.0.1")
    with caplog.at_level(logging.WARNING, logger="uacell.ua.door"):
        door.check_versions()  # no exception
    assert any("uvicorn" in r.getMessage() and "0.0.1" in r.getMessage() for r in caplog.records)


def test_attach_wraps_asyncua_once() -> None:
    from asyncua.server.uaprocessor import UaProcessor

    attach()
    first = UaProcessor.process_message
    attach()
    assert UaProcessor.process_message is first and set(INVENTORY) >= door.installed()


def test_binders_reach_the_address_space_by_typed_operations_only() -> None:
    from uacell.binding.space import Space

    assert not hasattr(Space, "aspace") and not hasattr(Space, "node")  # no AddressSpace, no Node handed out
    adapter = SRC / "ua"
    found = []
    for path in sorted(SRC.rglob("*.py")):
        if adapter in path.parents:
            continue
        text = path.read_text(encoding="utf-8")
        if re.search(r"from uacell\.ua\.space import [^\n]*\baddress_space\b", text):
            found.append(str(path.relative_to(SRC)))
    assert found == [], "binders use Space's operations, not the node store: " + ", ".join(found)


def test_docs_asyncua_lists_every_inventory_entry_and_the_verified_versions() -> None:
    doc = (SRC.parents[1] / "docs" / "asyncua.md").read_text(encoding="utf-8")
    for entry in ENTRIES:
        shown = re.sub(r"^asyncua\.(server|common|crypto)\.", "", entry.target)
        row = f"| `{shown}` | {entry.kind.value} | `{entry.owner}` | {entry.why} | {entry.replaces or '—'} |"
        assert row in doc, f"docs/asyncua.md's row for {entry.target} is not the inventory's: {row}"
    assert f"asyncua {door.VERIFIED['asyncua']}, uvicorn {door.VERIFIED['uvicorn']}" in doc
