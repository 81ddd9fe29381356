"""What a HistoryRead answers for a node it cannot read: ``HistoryError`` with the status code. The
WhereClause of ReadEventDetails is evaluated by ``uacell.ua.content_filter``, as a subscription's is."""

from __future__ import annotations

from asyncua import ua


class HistoryError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(ua.StatusCode(code).name)
        self.code = code
