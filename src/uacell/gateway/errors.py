"""The errors every gateway transport raises (Modbus, S7, Logix, OPC UA links, UR's Dashboard):
what a driver catches, whatever carries its tags."""

from __future__ import annotations


class CommunicationError(Exception):
    """The endpoint did not answer or answered with an error (message names the endpoint)."""


class NoAnswer(CommunicationError):
    """The endpoint did not answer at all (gone, frozen or out of reach): the connection is lost, not
    a request refused."""


class DashboardError(Exception):
    """UR's Dashboard Server cannot be reached or did not answer."""
