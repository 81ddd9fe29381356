"""Every companion of the build is a ``Companion[ServerView]``: what its binder and metrics factory are
declared to take, the server is (``uacell.host.ServerView``); its settings are a dataclass.

mypy checks the server against ``ServerView`` where it calls them (``uacell.server``); the functions
named by string (``lazy_binder``, ``lazy_metrics``) are checked here, against their annotations.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import sys
import typing
from collections.abc import Callable
from typing import Any

import pytest

import uacell.host
from uacell.catalog import companions
from uacell.core.companion import Companion, lazy_binder, lazy_metrics
from uacell.host import BinderHost, Host, ServerView


def _named(lazy: Callable[..., Any]) -> Callable[..., Any]:
    """The function a ``lazy_binder``/``lazy_metrics`` stands for (imported, as the server would)."""
    names = inspect.getclosurevars(lazy).nonlocals
    return typing.cast(Callable[..., Any], getattr(importlib.import_module(names["module"]), names["name"]))


def _takes(function: Callable[..., Any]) -> Any:
    """The annotated type of the function's one parameter (the server): ``uacell.host``'s Protocols are
    often imported under ``TYPE_CHECKING`` only, so the annotation is read with them at hand."""
    (parameter,) = inspect.signature(function).parameters.values()
    hint = parameter.annotation
    return eval(hint, {**vars(uacell.host), **function.__globals__}) if isinstance(hint, str) else hint


@pytest.mark.parametrize("companion", companions(), ids=lambda c: c.name)
def test_what_its_functions_take_the_server_view_is(companion: Companion[ServerView]) -> None:
    found = [_named(f) for f in (companion.binder, companion.metrics) if f is not None]
    assert companion.binder is not None and found
    for function in found:
        assert _takes(function) in ServerView.__mro__, (companion.name, function.__qualname__)


@pytest.mark.parametrize("companion", [c for c in companions() if c.settings is not None], ids=lambda c: c.name)
def test_its_settings_are_a_dataclass_of_optional_fields(companion: Companion[ServerView]) -> None:
    assert companion.settings is not None and dataclasses.is_dataclass(companion.settings)
    companion.settings()  # every field has its default


def test_the_check_refuses_a_function_that_takes_something_else() -> None:
    async def bind(app: int) -> None:
        return None

    module = sys.modules[__name__]
    module.__dict__["_odd_binder"] = bind
    try:
        taken = _takes(_named(lazy_binder(__name__, "_odd_binder")))
    finally:
        del module.__dict__["_odd_binder"]
    assert taken is int and taken not in ServerView.__mro__
    assert {Host, BinderHost} <= set(ServerView.__mro__)
    assert _named(lazy_metrics("uacell.packml.metrics", "packml_metrics")).__name__ == "packml_metrics"
