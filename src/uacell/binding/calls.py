"""What the method dispatcher keeps of a bound method, and the result of a call it answers itself."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from asyncua import ua

from uacell.core.roles import Family

Handler = Callable[..., Awaitable[Sequence[Any] | None]]
UNKNOWN = object()  # no executable_inputs
UNSCOPED = object()  # the scope of methods bound with neither ``scope`` nor ``serialize_on``


@dataclass
class BoundMethod:
    object_id: ua.NodeId
    method_id: ua.NodeId
    name: str
    family: Family
    handler: Handler  # handler(caller, *inputs) -> outputs (python values) or None
    inputs: list[ua.Argument]
    outputs: list[ua.Argument]
    executable: Callable[[], bool] | None = None
    serialize_on: object | None = None  # calls sharing this key run one at a time
    element: object | None = None  # what guards (locks) look at
    file_mode_argument: int | None = None  # FileType.Open: which argument is the mode
    # the model whose state decides ``executable`` (default: serialize_on); a call or a change
    # re-evaluates Executable only for the methods of the scope it touched (and those with no scope)
    scope: object | None = field(default=None, repr=False)
    last_executable: bool | None = field(default=None, repr=False)


def call_result(code: int, arg_results: list[ua.StatusCode] | None = None, n: int = 0) -> ua.CallMethodResult:
    r = ua.CallMethodResult()
    r.StatusCode = ua.StatusCode(code)
    r.InputArgumentResults = arg_results or []
    return r
