"""asyncua's own processing that uacell's replacements fall back on, reached through the door."""

from __future__ import annotations

from asyncua import ua
from asyncua.server.address_space import MethodService


async def asyncua_method_call(service: MethodService, request: ua.CallMethodRequest) -> ua.CallMethodResult:
    """asyncua's call of a method's callback (``MethodService._call``), for a method uacell does not bind."""
    result: ua.CallMethodResult = await MethodService._call(service, request)
    return result
