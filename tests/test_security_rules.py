"""Pure pieces of security.py: the refusal log's rate limit and the user token secret's nonce check."""

from __future__ import annotations

import logging
import struct

import pytest

from uacell.core.logs import RefusalLog
from uacell.security.policy import open_token_secret

NONCE = bytes(range(32))


def _secret(password: bytes, nonce: bytes) -> bytes:
    return struct.pack("<I", len(password) + len(nonce)) + password + nonce


def test_token_secret_gives_the_password_only_with_this_sessions_nonce() -> None:
    assert open_token_secret(_secret(b"p\xc3\xa4ss", NONCE) + b"\x00padding", NONCE) == b"p\xc3\xa4ss"
    other = bytes(reversed(NONCE))
    for plain, nonce in [
        (_secret(b"pass", other), NONCE),  # a token made for another session (a replay)
        (_secret(b"pass", NONCE), None),  # no nonce issued
        (_secret(b"pass", NONCE)[:-1], NONCE),  # length beyond the data
        (struct.pack("<I", 3) + b"abc", NONCE),  # shorter than a nonce
        (b"\x01", NONCE),
    ]:
        with pytest.raises(ValueError):
            open_token_secret(plain, nonce)


def test_refusal_log_reports_once_per_address_reason_and_interval(caplog: pytest.LogCaptureFixture) -> None:
    now = [0.0]
    refusals = RefusalLog(interval=60.0, clock=lambda: now[0])
    caplog.set_level(logging.INFO, logger="uacell.security.policy")
    assert refusals.report("10.0.0.9", "channel", "refused A")
    assert not refusals.report("10.0.0.9", "channel", "refused A")
    assert not refusals.report("10.0.0.9", "channel", "refused A")
    assert refusals.report("10.0.0.8", "channel", "refused B")  # another address
    assert refusals.report("10.0.0.9", "token", "refused C")  # another reason
    now[0] = 61.0
    assert refusals.report("10.0.0.9", "channel", "refused A")
    assert {r.levelno for r in caplog.records} == {logging.INFO}  # a client's doing, not the server's
    messages = [r.getMessage() for r in caplog.records]
    assert messages == [
        "refused A",
        "refused B",
        "refused C",
        "refused A (2 more such refusals from 10.0.0.9 not logged)",
    ]
