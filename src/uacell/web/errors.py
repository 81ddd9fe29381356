"""What the web HMI's OPC UA requests answer when they fail: a Bad status code (``CallFailed``), a key
the cell does not have (``UnknownKey``), and the words the login box says."""

from __future__ import annotations

from asyncua import ua

from uacell.core.errors import login_refusal as refused_login


class UnknownKey(LookupError):
    """The page named a method or directory this cell does not have."""


class CallFailed(Exception):
    """An OPC UA request answered with a Bad status code."""

    def __init__(self, code: int, context: str = "") -> None:
        self.code = code
        name, doc = status_text(code)
        super().__init__(f"{context}: {name}" if context else name)
        self.name = name
        self.doc = doc


def login_refusal(exc: CallFailed) -> str:
    """What the login box says when the server refused a login: plain words for wrong credentials."""
    words = refused_login(exc.name)
    return f"{words[0].upper()}{words[1:]}" if words else f"{exc.name}: {exc.doc}"


def status_text(code: int) -> tuple[str, str]:
    """The status code's name and meaning, as OPC UA defines them."""
    name, doc = ua.status_codes.get_name_and_doc(code)
    return name, doc
