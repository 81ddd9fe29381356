"""The WhereClause of an EventFilter (OPC 10000-4 7.7, ContentFilter), evaluated on an event's fields:
one evaluator for the events a subscription reports and those a HistoryRead returns (decision 82).

Operators: And, Or, Not, Equals, IsNull, GreaterThan, LessThan, GreaterThanOrEqual, LessThanOrEqual,
Between, InList, Like and OfType. OfType is true for an event of the type *or one of its subtypes*
(7.7.3); asyncua's live filter compared the type exactly, so a client filtering on BaseEventType, or
on ConditionType for alarms, was sent nothing; its Like raised and dropped every event, and its
Between compared the operands in the wrong order. A filter with an operator not evaluated here (Cast,
BitwiseAnd, BitwiseOr, RelatedTo, InView) or an ElementOperand that points nowhere is refused when
the item is made (``refusal``), not discovered event after event, and the EventFilterResult says which
element and which select clause is wrong and why (``event_filter_result``, decision 87).

Operands: a LiteralOperand's value, an ElementOperand's result, a SimpleAttributeOperand's field (by
its BrowsePath; without one, its NodeId attribute is the event's type). LocalizedTexts compare by
their text; values of types that do not order make an ordering operator false.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

from asyncua import ua
from asyncua.common.events import Event

from uacell.ua import numeric_range
from uacell.ua.door import enums
from uacell.ua.toolkit import supertype

_SC = ua.StatusCodes
_A = ua.AttributeIds
_F = ua.FilterOperator
# each operator evaluated here, with the number of operands it takes (InList: at least two)
_OPERANDS = {
    _F.And: 2, _F.Or: 2, _F.Not: 1, _F.Equals: 2, _F.IsNull: 1, _F.GreaterThan: 2, _F.LessThan: 2,
    _F.GreaterThanOrEqual: 2, _F.LessThanOrEqual: 2, _F.Between: 3, _F.InList: 2, _F.Like: 2, _F.OfType: 1,
}  # fmt: skip
_ORDERED = {
    _F.GreaterThan: lambda a, b: a > b,
    _F.LessThan: lambda a, b: a < b,
    _F.GreaterThanOrEqual: lambda a, b: a >= b,
    _F.LessThanOrEqual: lambda a, b: a <= b,
}

Field = Callable[[str], Any]  # an event's field by its name ("Severity", "EnabledState/Id"), None if absent


class FilterError(Exception):
    """A filter that cannot be evaluated; ``code`` is the status code to answer."""

    def __init__(self, code: int) -> None:
        super().__init__(ua.StatusCode(code).name)
        self.code = code


def field_name(operand: ua.SimpleAttributeOperand) -> str:
    """The name of the event field a SimpleAttributeOperand selects (asyncua's naming of event fields)."""
    return str(Event.browse_path_to_attribute_name(operand.BrowsePath))


def refusal(where: ua.ContentFilter | None) -> int | None:
    """Why a WhereClause cannot be evaluated here (a status code), or None."""
    return checked(where)[0]


def checked(where: ua.ContentFilter | None) -> tuple[int | None, list[ua.ContentFilterElementResult]]:
    """A WhereClause checked element by element (OPC 10000-4 7.7.2, ContentFilterResult): why the item is
    refused (Bad_MonitoredItemFilterUnsupported or Bad_MonitoredItemFilterInvalid; None when it can be
    evaluated), and each element's result, in the elements' order (empty when every element is right).
    An operator not evaluated here is Bad_FilterOperatorUnsupported, a wrong number of operands
    Bad_FilterOperandCountMismatch, an ElementOperand that points nowhere or an operand of a kind not
    evaluated here (an AttributeOperand) Bad_FilterOperandInvalid, with the operand's own code."""
    elements = list(where.Elements or ()) if where is not None else []
    refused: int | None = None
    results: list[ua.ContentFilterElementResult] = []
    for element in elements:
        code, operand_codes, why = _element_fault(element, len(elements))
        results.append(ua.ContentFilterElementResult(StatusCode=ua.StatusCode(code), OperandStatusCodes=operand_codes))
        if why is not None and refused is None:
            refused = why
    if refused is None:
        return None, []
    return refused, results


def _element_fault(element: Any, count: int) -> tuple[int, list[ua.StatusCode], int | None]:
    """One element's code, its operands' codes (empty when they are right) and the item's refusal."""
    if not enums.known(element.FilterOperator, _F):  # a number the standard does not define
        return int(_SC.BadFilterOperatorInvalid), [], int(_SC.BadMonitoredItemFilterInvalid)
    needed = _OPERANDS.get(element.FilterOperator)
    if needed is None:
        return int(_SC.BadFilterOperatorUnsupported), [], int(_SC.BadMonitoredItemFilterUnsupported)
    operands = element.FilterOperands or []
    if len(operands) < needed or (element.FilterOperator != _F.InList and len(operands) > needed):
        return int(_SC.BadFilterOperandCountMismatch), [], int(_SC.BadMonitoredItemFilterInvalid)
    codes = [_operand_fault(operand, count) for operand in operands]
    if not any(codes):
        return int(_SC.Good), [], None
    unsupported = any(not isinstance(o, _OPERAND_KINDS) for o in operands)
    why = _SC.BadMonitoredItemFilterUnsupported if unsupported else _SC.BadMonitoredItemFilterInvalid
    return int(_SC.BadFilterOperandInvalid), [ua.StatusCode(c) for c in codes], int(why)


_OPERAND_KINDS = (ua.ElementOperand, ua.LiteralOperand, ua.SimpleAttributeOperand)


def _operand_fault(operand: Any, count: int) -> int:
    """0 for an operand evaluated here, else Bad_FilterOperandInvalid."""
    if isinstance(operand, ua.ElementOperand) and not 0 <= operand.Index < count:
        return int(_SC.BadFilterOperandInvalid)
    if not isinstance(operand, _OPERAND_KINDS):
        return int(_SC.BadFilterOperandInvalid)  # an AttributeOperand
    return 0


def select_results(aspace: Any, selects: list[ua.SimpleAttributeOperand] | None) -> list[ua.StatusCode]:
    """Each select clause's result (OPC 10000-4 7.22.3), empty when every clause can be served: an
    unknown TypeDefinitionId is Bad_NodeIdUnknown, a node that is no ObjectType Bad_TypeDefinitionInvalid,
    an unknown AttributeId Bad_AttributeIdInvalid, an IndexRange that does not parse Bad_IndexRangeInvalid,
    a BrowsePath with an empty name Bad_BrowseNameInvalid. A clause that cannot be served selects a null
    field; the item is made."""
    codes = [_select_fault(aspace, clause) for clause in selects or ()]
    return [ua.StatusCode(code) for code in codes] if any(codes) else []


def _select_fault(aspace: Any, clause: ua.SimpleAttributeOperand) -> int:
    type_id = clause.TypeDefinitionId
    if type_id is not None and not type_id.is_null():
        node = aspace.get(type_id) if aspace is not None else None
        if node is None and aspace is not None:
            return int(_SC.BadNodeIdUnknown)
        if node is not None:
            kind = node.attributes.get(_A.NodeClass)
            if kind is None or kind.value.Value.Value != ua.NodeClass.ObjectType:
                return int(_SC.BadTypeDefinitionInvalid)
    if clause.AttributeId not in _ATTRIBUTE_IDS:
        return int(_SC.BadAttributeIdInvalid)
    if clause.IndexRange:
        try:
            numeric_range.parse(clause.IndexRange)
        except numeric_range.RangeError:
            return int(_SC.BadIndexRangeInvalid)
    if any(not name.Name for name in clause.BrowsePath or ()):
        return int(_SC.BadBrowseNameInvalid)
    return 0


_ATTRIBUTE_IDS = frozenset(int(a) for a in ua.AttributeIds)


def event_filter_result(aspace: Any, flt: ua.EventFilter) -> ua.EventFilterResult | None:
    """The EventFilterResult of an event item's filter (OPC 10000-4 7.22.3): the select clauses' and the
    WhereClause elements' results; None when nothing is wrong ("may be omitted if no errors occurred")."""
    _, elements = checked(flt.WhereClause)
    selects = select_results(aspace, flt.SelectClauses)
    if not elements and not selects:
        return None
    return ua.EventFilterResult(
        SelectClauseResults=selects, WhereClauseResult=ua.ContentFilterResult(ElementResults=elements)
    )


class WhereClause:
    """Evaluates ContentFilters on events; an event type's supertypes are looked up once."""

    def __init__(self, aspace: Any) -> None:
        self.aspace = aspace  # None: no type hierarchy, OfType names the event's own type only
        self._supertypes: dict[ua.NodeId, frozenset[ua.NodeId]] = {}

    def matches(self, where: ua.ContentFilter | None, field: Field, etype: ua.NodeId | None) -> bool:
        """Does an event of type ``etype`` with these fields pass ``where``? FilterError when the filter
        cannot be evaluated."""
        if where is None or not where.Elements:
            return True
        return bool(self._eval(where.Elements, 0, field, etype))

    def _is_subtype(self, etype: ua.NodeId | None, of: ua.NodeId) -> bool:
        if etype is None:
            return False
        types = self._supertypes.get(etype)
        if types is None:
            seen: set[ua.NodeId] = set()
            t: ua.NodeId | None = etype
            while t is not None and t not in seen:
                seen.add(t)
                t = supertype(self.aspace, t) if self.aspace is not None else None
            types = frozenset(seen)
            self._supertypes[etype] = types
        return of in types

    def _operand(self, op: Any, elements: list[Any], field: Field, etype: ua.NodeId | None) -> Any:
        if isinstance(op, ua.LiteralOperand):
            return op.Value.Value
        if isinstance(op, ua.ElementOperand):
            return self._eval(elements, op.Index, field, etype)
        if isinstance(op, ua.SimpleAttributeOperand):
            if not op.BrowsePath:
                return etype if op.AttributeId == _A.NodeId else None
            return field(field_name(op))
        raise FilterError(_SC.BadFilterOperandInvalid)

    def _eval(self, elements: list[Any], index: int, field: Field, etype: ua.NodeId | None) -> Any:
        if not 0 <= index < len(elements):
            raise FilterError(_SC.BadFilterOperandInvalid)
        element = elements[index]
        op = element.FilterOperator
        args = element.FilterOperands or []
        if op not in _OPERANDS:
            raise FilterError(_SC.BadFilterOperatorUnsupported if enums.known(op, _F) else _SC.BadFilterOperatorInvalid)
        if op == _F.OfType:
            target = self._operand(args[0], elements, field, etype)
            return isinstance(target, ua.NodeId) and self._is_subtype(etype, target)
        vals = [self._operand(a, elements, field, etype) for a in args]
        if op == _F.And:
            return bool(vals[0]) and bool(vals[1])
        if op == _F.Or:
            return bool(vals[0]) or bool(vals[1])
        if op == _F.Not:
            return not vals[0]
        if op == _F.IsNull:
            return vals[0] is None
        if op == _F.Equals:
            return _same(vals[0], vals[1])
        if op == _F.InList:
            return any(_same(vals[0], v) for v in vals[1:])
        if op == _F.Like:
            return isinstance(_text(vals[0]), str) and like(_text(vals[1])).fullmatch(_text(vals[0])) is not None
        try:
            if op == _F.Between:
                return bool(vals[1] <= vals[0] <= vals[2])
            return bool(_ORDERED[op](vals[0], vals[1]))
        except TypeError:  # values that do not order
            return False


def like(pattern: Any) -> re.Pattern[str]:
    """The regular expression of a Like pattern (OPC 10000-4 7.7.3): ``%`` any text, ``_`` one character,
    ``[...]`` one of the characters listed (``[^...]`` one not listed), ``\\`` the next character as it is."""
    if not isinstance(pattern, str):
        return re.compile(r"(?!)")  # matches nothing
    out, i = [], 0
    while i < len(pattern):
        c = pattern[i]
        if c == "\\" and i + 1 < len(pattern):
            out.append(re.escape(pattern[i + 1]))
            i += 2
            continue
        if c == "%":
            out.append(".*")
        elif c == "_":
            out.append(".")
        elif c == "[":
            end = pattern.find("]", i + 1)
            if end < 0:
                out.append(re.escape(c))
            else:
                body = pattern[i + 1 : end]
                negate = body.startswith("^")
                chars = "".join(re.escape(ch) if ch != "-" else "-" for ch in (body[1:] if negate else body))
                out.append(f"[{'^' if negate else ''}{chars}]")
                i = end
        else:
            out.append(re.escape(c))
        i += 1
    return re.compile("".join(out), re.DOTALL)


def _text(value: Any) -> Any:
    return value.Text if isinstance(value, ua.LocalizedText) else value


def _same(a: Any, b: Any) -> bool:
    return bool(_text(a) == _text(b))
