"""When a monitored item reports a value (OPC 10000-4 7.22.2 DataChangeFilter, 7.10 DataChangeTrigger),
as the standard's text says, against the pure rule of ``uacell.ua.datachange``."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

import pytest
from asyncua import ua
from asyncua.ua import uaprotocol_auto

from uacell.ua.datachange import reported

_T0 = datetime(2026, 11, 28, 12, 0, tzinfo=UTC)
_GOOD = ua.StatusCode(ua.StatusCodes.Good)
_UNCERTAIN = ua.StatusCode(ua.StatusCodes.UncertainLastUsableValue)


def dv(
    value: Any,
    vtype: ua.VariantType = ua.VariantType.Double,
    status: ua.StatusCode = _GOOD,
    at: datetime = _T0,
) -> ua.DataValue:
    variant = ua.Variant(value, vtype, is_array=isinstance(value, list))
    return ua.DataValue(variant, StatusCode=status, SourceTimestamp=at)


def band(value: float, trigger: ua.DataChangeTrigger = ua.DataChangeTrigger.StatusValue) -> Any:
    # what a client's filter decodes to on the server (asyncua's ua.DataChangeFilter is a subclass)
    return uaprotocol_auto.DataChangeFilter(Trigger=trigger, DeadbandType=ua.DeadbandType.Absolute, DeadbandValue=value)


def trigger(which: ua.DataChangeTrigger) -> Any:
    return uaprotocol_auto.DataChangeFilter(Trigger=which)


def test_the_first_value_is_reported() -> None:
    assert reported(None, dv(1.0), None)
    assert reported(None, dv(1.0), band(5.0))


def test_without_a_filter_a_change_of_value_or_status_is_reported_and_a_new_timestamp_alone_is_not() -> None:
    assert not reported(dv(1.0), dv(1.0, at=_T0 + timedelta(seconds=1)), None)
    assert reported(dv(1.0), dv(1.5), None)
    assert reported(dv(1.0), dv(1.0, status=_UNCERTAIN), None)
    assert reported(dv(1, ua.VariantType.Int32), dv(1.0, ua.VariantType.Double), None)  # another type


def test_a_deadband_compares_with_the_last_value_reported() -> None:
    """ "Generate a Notification if (absolute value of (last cached value - current value) >
    AbsoluteDeadband)": the caller passes the last value reported, so a slow drift adds up."""
    last = dv(100.0)
    drift = [100.5, 100.9, 101.2, 101.9]
    got = []
    for value in drift:
        if reported(last, dv(value), band(1.0)):
            got.append(value)
            last = dv(value)
    assert got == [101.2]  # 1.2 from 100; 101.9 is 0.7 from 101.2
    assert not reported(dv(100.0), dv(101.0), band(1.0))  # exactly the deadband: not beyond it
    assert reported(dv(100.0), dv(98.9), band(1.0))
    assert reported(dv(10, ua.VariantType.Int32), dv(12, ua.VariantType.Int32), band(1.0))
    assert reported(dv(1.0), dv(1.001), band(0.0))  # a deadband of 0: every change


def test_a_change_of_status_is_reported_whatever_the_deadband() -> None:
    """ "Deadband is ignored if the status of the data item changes." """
    assert reported(dv(100.0), dv(100.0, status=_UNCERTAIN), band(1.0))
    assert reported(dv(100.0, status=_UNCERTAIN), dv(100.2), band(1.0))


def test_the_status_trigger_reports_only_status_changes() -> None:
    status_only = trigger(ua.DataChangeTrigger.Status)
    assert not reported(dv(1.0), dv(2.0), status_only)
    assert reported(dv(1.0), dv(1.0, status=_UNCERTAIN), status_only)


def test_the_timestamp_trigger_reports_a_new_source_timestamp_but_not_with_a_deadband() -> None:
    """STATUS_VALUE_TIMESTAMP: "If a Deadband filter is specified, this trigger has the same
    behaviour as STATUS_VALUE_1" (OPC 10000-4 7.10)."""
    later = _T0 + timedelta(seconds=1)
    assert reported(dv(1.0), dv(1.0, at=later), trigger(ua.DataChangeTrigger.StatusValueTimestamp))
    assert not reported(dv(1.0), dv(1.0), trigger(ua.DataChangeTrigger.StatusValueTimestamp))
    assert not reported(dv(1.0), dv(1.5, at=later), band(1.0, ua.DataChangeTrigger.StatusValueTimestamp))


def test_nan_is_reported_once_when_it_begins() -> None:
    """ "For floating point values a Server shall check for NaN and only report a single
    notification with NaN when the value enters the NaN state." """
    nan = float("nan")
    assert reported(dv(1.0), dv(nan), None)
    assert not reported(dv(nan), dv(float("nan")), None)
    assert not reported(dv(nan), dv(float("nan")), band(1.0))
    assert reported(dv(nan), dv(1.0), band(1.0))
    assert not reported(dv([1.0, nan]), dv([1.0, float("nan")]), None)


def test_an_array_is_reported_when_its_length_changes_or_an_element_leaves_the_deadband() -> None:
    """ "If the item is an array of values, the entire array is returned if any array element exceeds
    the AbsoluteDeadband, or the size or dimension of the array changes." """
    assert not reported(dv([1.0, 2.0]), dv([1.5, 2.5]), band(1.0))
    assert reported(dv([1.0, 2.0]), dv([1.0, 3.5]), band(1.0))
    assert reported(dv([1.0, 2.0]), dv([1.0, 2.0, 3.0]), band(1.0))
    assert reported(dv([1.0, 2.0]), dv([1.0, 2.5]), None)  # no deadband: any element
    assert not reported(dv([1.0, 2.0]), dv([1.0, 2.0]), None)


@pytest.mark.parametrize(
    ("old", "new", "vtype", "expected"),
    [
        ("Idle", "Idle", ua.VariantType.String, False),
        ("Idle", "Ready", ua.VariantType.String, True),  # not a number: the deadband compares for equality
        (True, False, ua.VariantType.Boolean, True),
    ],
)
def test_a_deadband_on_a_value_that_is_not_a_number_compares_for_equality(
    old: Any, new: Any, vtype: ua.VariantType, expected: bool
) -> None:
    assert reported(dv(old, vtype), dv(new, vtype), band(5.0)) is expected


def test_a_percent_deadband_is_not_applied() -> None:
    """PercentDeadband needs the variable's EURange (OPC 10000-8): every change is reported."""
    percent = uaprotocol_auto.DataChangeFilter(
        Trigger=ua.DataChangeTrigger.StatusValue, DeadbandType=ua.DeadbandType.Percent, DeadbandValue=50.0
    )
    assert reported(dv(1.0), dv(1.1), percent)
    assert not reported(dv(1.0), dv(1.0), percent)
