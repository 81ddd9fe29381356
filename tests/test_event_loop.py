"""``[server] event_loop``: the event loop `uacell serve` runs on (auto, uvloop, asyncio), checked like
every other setting, and the server answers on either loop."""

from __future__ import annotations

import asyncio

import pytest
from asyncua import Client, ua
from conftest import start_serve

from uacell.config import Config, load_config, validate
from uacell.core import early
from uacell.core.errors import ConfigError


async def _loop_module() -> str:
    return type(asyncio.get_running_loop()).__module__


@pytest.mark.parametrize(("setting", "module"), [("asyncio", "asyncio"), ("uvloop", "uvloop"), ("auto", "uvloop")])
def test_run_uses_the_loop_the_setting_names(monkeypatch, setting, module):
    monkeypatch.delenv(early.EVENT_LOOP_ENV, raising=False)
    assert early.run(_loop_module(), setting).startswith(module)


def test_the_environment_overrides_the_file(monkeypatch):
    monkeypatch.setenv(early.EVENT_LOOP_ENV, "asyncio")
    assert early.event_loop_name("uvloop") == "asyncio"
    assert early.run(_loop_module(), "uvloop").startswith("asyncio")


def test_auto_is_asyncio_where_uvloop_is_missing(monkeypatch):
    monkeypatch.delenv(early.EVENT_LOOP_ENV, raising=False)
    monkeypatch.setattr(early, "uvloop_installed", lambda: False)
    assert early.event_loop_name("auto") == "asyncio"


def test_the_setting_is_read_and_checked(tmp_path, monkeypatch):
    monkeypatch.delenv(early.EVENT_LOOP_ENV, raising=False)
    cfg = tmp_path / "uacell.toml"
    cfg.write_text('[server]\nevent_loop = "AsyncIO"\n')
    assert load_config(cfg).server.event_loop == "asyncio"
    assert Config().server.event_loop == "auto"
    cfg.write_text('[server]\nevent_loop = "tokio"\n')
    with pytest.raises(ConfigError, match=r"\[server\] event_loop: must be one of auto, uvloop, asyncio, not 'tokio'"):
        load_config(cfg)
    cfg.write_text("[server]\nevent_loop = 1\n")
    with pytest.raises(ConfigError, match=r"\[server\] event_loop: must be a string"):
        load_config(cfg)


def test_uvloop_named_where_it_is_not_installed_is_refused_with_the_fix(tmp_path, monkeypatch):
    import uacell.config as config_module

    monkeypatch.delenv(early.EVENT_LOOP_ENV, raising=False)
    monkeypatch.setattr(config_module, "uvloop_installed", lambda: False)
    cfg = tmp_path / "uacell.toml"
    cfg.write_text('[server]\nevent_loop = "uvloop"\n')
    with pytest.raises(ConfigError, match="uvloop is not installed: pip install uvloop, or choose auto or asyncio"):
        load_config(cfg)


def test_a_bad_environment_value_is_refused(monkeypatch):
    monkeypatch.setenv(early.EVENT_LOOP_ENV, "fast")
    with pytest.raises(ConfigError, match=r"\$UACELL_EVENT_LOOP: must be one of auto, uvloop, asyncio, not 'fast'"):
        validate(Config())


@pytest.mark.parametrize("setting", ["asyncio", "uvloop"])
async def test_serve_runs_and_answers_on_the_chosen_loop(tmp_path, setting):
    cfg = tmp_path / "uacell.toml"
    cfg.write_text(f'[server]\nevent_loop = "{setting}"\n')
    # an empty $UACELL_EVENT_LOOP is no choice: the file's stands
    sp = start_serve(tmp_path / "data", "--config", str(cfg), env={early.EVENT_LOOP_ENV: ""}, log_level="INFO")
    try:
        assert any(line.rstrip().endswith(f"event loop: {setting}") for line in sp.output), "".join(sp.output)
        async with Client(sp.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            packml = await client.get_namespace_index("http://opcfoundation.org/UA/PackML/")
            filler = client.get_node(ua.NodeId("Filler1", ns))
            method = await filler.get_child(f"{packml}:SetMachSpeed")
            await filler.call_method(method, ua.Variant(150.0, ua.VariantType.Float))
            speed = await client.get_node(ua.NodeId("Filler1.Status.MachSpeed", ns)).read_value()
            assert speed == 150.0
    finally:
        code = sp.stop()
    assert code == 0  # a clean stop on SIGTERM


async def test_the_tests_run_on_the_loop_uacell_serve_runs_on() -> None:
    """conftest's loop factory: in-process servers meet the loop they meet in service (decision 105)."""
    assert (await _loop_module()).startswith(early.event_loop_name())
