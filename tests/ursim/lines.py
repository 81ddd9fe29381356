"""A line protocol on a loopback TCP port: an optional greeting, then one reply line per line.

Shared by the Dashboard Server and the control port. ``stop`` closes the port and drops every open
connection unanswered, the way a controller that goes away does.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Generic, TypeVar

S = TypeVar("S")
TOO_LONG = "\ufffd"  # what a handler sees for a line over the reader's limit (64 KiB)


class LineServer(Generic[S]):
    """Subclasses give the greeting, a per-connection session and the reply to each line."""

    def __init__(self, port: int = 0, host: str = "127.0.0.1") -> None:
        self.host, self.port = host, port
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._tasks: set[asyncio.Task[object]] = set()

    def greeting(self) -> str | None:
        return None

    def session(self) -> S:
        raise NotImplementedError

    async def reply(self, session: S, line: str) -> tuple[str, bool]:
        """The reply line and whether to close the connection after it."""
        raise NotImplementedError

    @property
    def listening(self) -> bool:
        return self._server is not None

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, self.host, self.port, reuse_address=True)
        self.port = self._server.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            server.close()
        for writer in list(self._writers):
            writer.close()
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        if server is not None:
            await server.wait_closed()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        self._writers.add(writer)
        session = self.session()
        try:
            if (greeting := self.greeting()) is not None:
                writer.write((greeting + "\n").encode())
                await writer.drain()
            closing = False
            while not closing:
                try:
                    raw = await reader.readline()
                except ValueError:  # over the limit: the reader dropped it
                    raw = TOO_LONG.encode() + b"\n"
                if not raw.endswith(b"\n"):
                    return  # the client went away (a last unterminated line is not a command)
                answer, closing = await self.reply(session, raw.decode("utf-8", "replace"))
                writer.write((answer + "\n").encode())
                await writer.drain()
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self._writers.discard(writer)
            self._tasks.discard(task)
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()
