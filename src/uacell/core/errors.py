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


WRONG_CREDENTIALS = "the user name or password is wrong"

# How a refused login reads to a person (HMI, ``uacell health``): the status code's own text ("User
# does not have permission to perform the requested operation") says nothing about a typo.
_LOGIN_REFUSALS = {
    "BadUserAccessDenied": WRONG_CREDENTIALS,
    "BadIdentityTokenInvalid": "the server could not read the login (its token was refused as invalid)",
    "BadIdentityTokenRejected": "the server does not take a user name and password over this connection",
}


def login_refusal(status: str) -> str | None:
    """Plain words for a login refused with ``status`` (a StatusCode name); None for other refusals."""
    return _LOGIN_REFUSALS.get(status)
