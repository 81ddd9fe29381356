"""Errors the pure behaviour raises; the method dispatcher turns them into OPC UA status codes.

Behaviour stays free of the OPC UA stack: it names a status code ("BadInvalidState") and, where one
argument is at fault, which one. The dispatcher answers the call with that code and sets
``InputArgumentResults`` accordingly.
"""

from __future__ import annotations


class CallError(Exception):
    """Refuse a method call with ``status`` (an OPC UA StatusCode name such as ``"BadInvalidState"``).

    ``argument`` is the index of the offending input argument, if one is at fault; ``argument_status``
    is the code reported for it in InputArgumentResults (defaults to ``status``).
    """

    def __init__(
        self,
        status: str,
        message: str = "",
        *,
        argument: int | None = None,
        argument_status: str | None = None,
    ) -> None:
        super().__init__(message or status)
        self.status = status
        self.message = message or status
        self.argument = argument
        self.argument_status = argument_status or status


class ConfigError(Exception):
    """The configuration cannot be read or is not valid."""
