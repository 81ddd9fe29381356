"""The WhereClause of a HistoryRead of events (OPC 10000-4 ContentFilter, the operators history
supports), evaluated on a stored event's fields; its errors are HistoryRead status codes."""

from __future__ import annotations

from typing import Any

from asyncua import ua
from asyncua.common.events import Event

from uacell.ua.toolkit import supertype

_SC = ua.StatusCodes
_A = ua.AttributeIds


class HistoryError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(ua.StatusCode(code).name)
        self.code = code


class WhereClause:
    """Evaluates a ContentFilter on an event's fields; an event type's supertypes are looked up once."""

    def __init__(self, iserver: Any) -> None:
        self.iserver = iserver
        self._supertypes: dict[str, frozenset[str]] = {}

    def _is_subtype(self, etype: str, of: ua.NodeId) -> bool:
        types = self._supertypes.get(etype)
        if types is None:
            seen: set[str] = set()
            t: ua.NodeId | None = ua.NodeId.from_string(etype) if etype else None
            while t is not None and t.to_string() not in seen:
                seen.add(t.to_string())
                t = supertype(self.iserver.aspace, t)
            types = frozenset(seen)
            self._supertypes[etype] = types
        return of.to_string() in types

    def matches(self, where: ua.ContentFilter | None, fields: dict[str, ua.Variant], etype: str) -> bool:
        if where is None or not where.Elements:
            return True
        return bool(self._eval(where.Elements, 0, fields, etype))

    def _operand(self, op: Any, elements: list[Any], fields: dict[str, ua.Variant], etype: str) -> Any:
        if isinstance(op, ua.LiteralOperand):
            return op.Value.Value
        if isinstance(op, ua.ElementOperand):
            return self._eval(elements, op.Index, fields, etype)
        if isinstance(op, ua.SimpleAttributeOperand):
            if not op.BrowsePath:
                return ua.NodeId.from_string(etype) if op.AttributeId == _A.NodeId and etype else None
            name = Event.browse_path_to_attribute_name(op.BrowsePath)
            v = fields.get(name)
            return v.Value if v is not None else None
        raise HistoryError(_SC.BadFilterOperandInvalid)

    def _eval(self, elements: list[Any], index: int, fields: dict[str, ua.Variant], etype: str) -> Any:
        if not 0 <= index < len(elements):
            raise HistoryError(_SC.BadFilterOperandInvalid)
        el = elements[index]
        op = el.FilterOperator
        args = el.FilterOperands
        F = ua.FilterOperator
        if op == F.OfType:
            target = self._operand(args[0], elements, fields, etype)
            return isinstance(target, ua.NodeId) and self._is_subtype(etype, target)
        vals = [self._operand(a, elements, fields, etype) for a in args]
        if op == F.And:
            return bool(vals[0]) and bool(vals[1])
        if op == F.Or:
            return bool(vals[0]) or bool(vals[1])
        if op == F.Not:
            return not vals[0]
        if op == F.Equals:
            return _same(vals[0], vals[1])
        if op == F.InList:
            return any(_same(vals[0], v) for v in vals[1:])
        if op in (F.GreaterThan, F.LessThan, F.GreaterThanOrEqual, F.LessThanOrEqual):
            try:
                a, b = vals
                return {
                    F.GreaterThan: a > b,
                    F.LessThan: a < b,
                    F.GreaterThanOrEqual: a >= b,
                    F.LessThanOrEqual: a <= b,
                }[op]
            except TypeError:
                return False
        raise HistoryError(_SC.BadFilterOperatorUnsupported)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, ua.LocalizedText):
        a = a.Text
    if isinstance(b, ua.LocalizedText):
        b = b.Text
    return bool(a == b)
