"""The tests' own port picker: two asks never get one port, and xdist workers never share a slice.

CI once failed on one test asking ``free_port()`` twice and getting the same port for its Dashboard and its
Modbus server (2026-11-28); these guard the picker every listening test relies on.
"""

from __future__ import annotations

import socket

import helpers
import pytest
from helpers import free_port


def test_a_process_never_gets_the_same_port_twice() -> None:
    ports = [free_port() for _ in range(500)]
    assert len(set(ports)) == len(ports)


def test_a_port_something_listens_on_is_skipped() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        for _ in range(300):
            assert free_port() != taken.getsockname()[1]


def test_each_xdist_worker_has_a_slice_of_its_own_below_the_ephemeral_range(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "3")
    slices = []
    for worker in ("gw0", "gw1", "gw2"):
        monkeypatch.setenv("PYTEST_XDIST_WORKER", worker)
        slices.append(set(helpers._own_ports()))
    assert all(len(s) > 1000 for s in slices)
    assert not slices[0] & slices[1] and not slices[1] & slices[2] and not slices[0] & slices[2]
    assert max(max(s) for s in slices) < helpers._EPHEMERAL.start
    monkeypatch.delenv("PYTEST_XDIST_WORKER")  # outside xdist: the whole range
    assert set(helpers._own_ports()) >= slices[0] | slices[1] | slices[2]
