"""The WhereClause of an EventFilter (OPC 10000-4 7.7), as pure functions: the Like patterns of 7.7.3, the
operators evaluated on an event's fields, and the filters refused when an item is made (decision 82)."""

from __future__ import annotations

from typing import Any

import pytest
from asyncua import ua

from uacell.ua import content_filter
from uacell.ua.content_filter import WhereClause, like, refusal

SC = ua.StatusCodes
F = ua.FilterOperator


@pytest.mark.parametrize(
    ("pattern", "text", "matches"),
    [
        ("%Stop%", "Filler1 Stopped", True),
        ("Stop%", "Filler1 Stopped", False),
        ("Fill_r1", "Filler1", True),
        ("Fill_r1", "Fillr1", False),
        ("[FG]iller1", "Giller1", True),
        ("[^FG]iller1", "Giller1", False),
        ("[^FG]iller1", "Killer1", True),
        ("100\\%", "100%", True),
        ("100\\%", "1000", False),
        ("a.b", "axb", False),  # a regular expression's characters are themselves
        ("%", "", True),
    ],
)
def test_like_patterns(pattern: str, text: str, matches: bool) -> None:
    assert (like(pattern).fullmatch(text) is not None) is matches


def _field(fields: dict[str, Any]) -> content_filter.Field:
    return fields.get


def _attribute(name: str) -> ua.SimpleAttributeOperand:
    return ua.SimpleAttributeOperand(
        TypeDefinitionId=ua.NodeId(ua.ObjectIds.BaseEventType),
        BrowsePath=[ua.QualifiedName(name, 0)],
        AttributeId=ua.AttributeIds.Value,
    )


def _literal(value: Any) -> ua.LiteralOperand:
    return ua.LiteralOperand(Value=ua.Variant(value))


def _where(*elements: tuple[ua.FilterOperator, list[Any]]) -> ua.ContentFilter:
    return ua.ContentFilter(Elements=[ua.ContentFilterElement(FilterOperator=o, FilterOperands=a) for o, a in elements])


def test_operators_on_an_events_fields() -> None:
    where = WhereClause(aspace=None)
    event = _field({"Severity": 500, "Message": ua.LocalizedText("Filler1 Stopped"), "Comment": None})

    def passes(*elements: tuple[ua.FilterOperator, list[Any]]) -> bool:
        return where.matches(_where(*elements), event, None)

    assert passes((F.Between, [_attribute("Severity"), _literal(400), _literal(600)]))
    assert not passes((F.Between, [_attribute("Severity"), _literal(600), _literal(900)]))
    assert passes((F.Like, [_attribute("Message"), _literal("%Stopped")]))  # a LocalizedText by its text
    assert passes((F.Equals, [_attribute("Message"), _literal("Filler1 Stopped")]))
    assert passes((F.IsNull, [_attribute("Comment")])) and passes((F.IsNull, [_attribute("Missing")]))
    assert passes((F.InList, [_attribute("Severity"), _literal(100), _literal(500)]))
    assert not passes((F.GreaterThan, [_attribute("Message"), _literal(3)]))  # no order: false
    assert passes(
        (F.And, [ua.ElementOperand(Index=1), ua.ElementOperand(Index=2)]),
        (F.GreaterThanOrEqual, [_attribute("Severity"), _literal(500)]),
        (F.Not, [ua.ElementOperand(Index=3)]),
        (F.LessThan, [_attribute("Severity"), _literal(100)]),
    )
    assert where.matches(None, event, None) and where.matches(ua.ContentFilter(), event, None)


def test_filters_that_cannot_be_evaluated_are_refused() -> None:
    assert refusal(None) is None
    assert refusal(_where((F.Like, [_attribute("Message"), _literal("%")]))) is None
    assert (
        refusal(_where((F.BitwiseAnd, [_attribute("Severity"), _literal(1)]))) == SC.BadMonitoredItemFilterUnsupported
    )
    assert (
        refusal(_where((F.Cast, [_attribute("Severity"), _literal(ua.NodeId(6))])))
        == SC.BadMonitoredItemFilterUnsupported
    )
    assert refusal(_where((F.Not, [ua.ElementOperand(Index=4)]))) == SC.BadMonitoredItemFilterInvalid
    assert refusal(_where((F.Equals, [_attribute("Severity")]))) == SC.BadMonitoredItemFilterInvalid  # one operand
    assert refusal(_where((F.Not, [ua.AttributeOperand()]))) == SC.BadMonitoredItemFilterUnsupported


def test_each_element_of_a_refused_where_clause_has_its_result() -> None:
    """OPC 10000-4 7.7.2 (decision 87): one result per element, in order, with the operands' codes where
    an operand is wrong; nothing when every element can be evaluated."""
    fine = (F.Like, [_attribute("Message"), _literal("%")])
    refused, results = content_filter.checked(
        _where(
            (F.And, [ua.ElementOperand(Index=1), ua.ElementOperand(Index=2)]),
            fine,
            (F.Not, [ua.ElementOperand(Index=9)]),
            (F.BitwiseAnd, [_attribute("Severity"), _literal(1)]),
            (F.Equals, [_attribute("Severity")]),
            (F.Not, [ua.AttributeOperand()]),
        )
    )
    assert refused == SC.BadMonitoredItemFilterInvalid  # the first element at fault says it
    assert [(r.StatusCode.value, [c.value for c in r.OperandStatusCodes]) for r in results] == [
        (SC.Good, []),
        (SC.Good, []),
        (SC.BadFilterOperandInvalid, [SC.BadFilterOperandInvalid]),
        (SC.BadFilterOperatorUnsupported, []),
        (SC.BadFilterOperandCountMismatch, []),
        (SC.BadFilterOperandInvalid, [SC.BadFilterOperandInvalid]),
    ]
    assert content_filter.checked(_where(fine)) == (None, [])


def test_select_clauses_are_checked_without_an_address_space_only_by_their_form() -> None:
    def clause(**fields: Any) -> ua.SimpleAttributeOperand:
        values = {"BrowsePath": [ua.QualifiedName("Severity", 0)], "AttributeId": ua.AttributeIds.Value, **fields}
        return ua.SimpleAttributeOperand(**values)

    assert content_filter.select_results(None, [clause(), clause(IndexRange="1:2")]) == []
    codes = content_filter.select_results(
        None, [clause(), clause(AttributeId=0), clause(IndexRange="2:1"), clause(BrowsePath=[ua.QualifiedName("")])]
    )
    assert [c.value for c in codes] == [
        SC.Good, SC.BadAttributeIdInvalid, SC.BadIndexRangeInvalid, SC.BadBrowseNameInvalid,
    ]  # fmt: skip
