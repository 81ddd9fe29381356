"""How many OPC UA sessions the web HMI holds on its server at once (``[web] ua_sessions``)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable

CONNECTS_AT_ONCE = 8  # OPC UA connections the HMI opens at once (handshake and activation)


class SessionSlots:
    """The OPC UA sessions an HMI may hold on the server at once (``[web] ua_sessions``).

    A ``UaSession`` takes a slot before it connects and gives it back only once its client is
    disconnected and no connect of it is under way, so the server never holds more sessions of this
    HMI than there are slots, whatever the concurrency. ``take`` and ``give`` never await: checking
    and taking happen in one step of the event loop. ``on_free`` is told whenever a slot came free.
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.holders: set[object] = set()
        self.on_free: Callable[[], None] | None = None
        self._freed = asyncio.Event()
        # Connections of one address that have not activated a session yet are what a server evicts
        # first ([limits] pending_per_address, 32 in uacell): the HMI opens only a few at once.
        self.connecting = asyncio.Semaphore(CONNECTS_AT_ONCE)

    def take(self, holder: object) -> bool:
        if holder in self.holders:
            return True
        if len(self.holders) >= self.capacity:
            return False
        self.holders.add(holder)
        return True

    def give(self, holder: object) -> None:
        if holder in self.holders:
            self.holders.discard(holder)
            self._freed.set()
            self._freed = asyncio.Event()
            if self.on_free is not None:
                self.on_free()

    async def wait_take(self, holder: object, timeout: float) -> bool:
        """``take``, waiting up to ``timeout`` seconds for a slot to come free."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while not self.take(holder):
            remaining = deadline - loop.time()
            if remaining <= 0:
                return False
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._freed.wait(), remaining)
        return True

    @property
    def free(self) -> int:
        return self.capacity - len(self.holders)
