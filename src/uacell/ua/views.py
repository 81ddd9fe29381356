"""Browse, BrowseNext and TranslateBrowsePathsToNodeIds as OPC 10000-4 5.9 describes them (decision 81).

asyncua's View services differ from the standard where clients notice:

- Browse ignored RequestedMaxReferencesPerNode (every reference came back at once) and had no
  BrowseNext at all, so a client that pages a large folder got more than it asked for, and one that
  sent BrowseNext was refused;
- an unknown node was Bad_NodeIdInvalid (that code is for a NodeId that is not well formed:
  Bad_NodeIdUnknown is the one for a node that does not exist), an unknown ReferenceTypeId or one that
  names no ReferenceType found nothing instead of Bad_ReferenceTypeIdInvalid, an unknown View browsed
  the whole address space instead of Bad_ViewIdUnknown, and ResultMask was not applied;
- TranslateBrowsePathsToNodeIds failed the whole request (Bad_InternalError) for an empty RelativePath,
  and refused an empty TargetName in the last element, which the standard allows (every target of the
  element's references), while accepting one in the other elements, which it forbids.

Here: a Browse returns at most RequestedMaxReferencesPerNode references of a node (0: no limit) and a
continuation point for the rest; BrowseNext returns the next ones or releases them. Continuation points
belong to their session (another session's is Bad_ContinuationPointInvalid, as an unknown one), at most
``MAX_BROWSE_CONTINUATION_POINTS`` a session (ServerCapabilities.MaxBrowseContinuationPoints; one more is
Bad_NoContinuationPoints), and go with the session. A continuation point keeps the references the
Browse found: BrowseNext answers from them, as they were then.

``StandardViews`` is a mixin of uacell's session (``uacell.ua.limits.LimitedSession``).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from typing import Any

from asyncua import ua
from asyncua.common.utils import ServiceError

from uacell.ua import door

#: Continuation points a session may hold at once (Browse's and BrowseNext's).
MAX_BROWSE_CONTINUATION_POINTS = 16

_A = ua.AttributeIds
_SC = ua.StatusCodes
_HAS_SUBTYPE = ua.NodeId(ua.ObjectIds.HasSubtype)
_DIRECTIONS = frozenset({ua.BrowseDirection.Forward, ua.BrowseDirection.Inverse, ua.BrowseDirection.Both})
_ALL_FIELDS = int(ua.BrowseResultMask.All)
# ResultMask bit -> the ReferenceDescription field it keeps
_MASKED_FIELDS = {
    int(ua.BrowseResultMask.ReferenceTypeId): "ReferenceTypeId",
    int(ua.BrowseResultMask.IsForward): "IsForward",
    int(ua.BrowseResultMask.NodeClass): "NodeClass",
    int(ua.BrowseResultMask.BrowseName): "BrowseName",
    int(ua.BrowseResultMask.DisplayName): "DisplayName",
    int(ua.BrowseResultMask.TypeDefinition): "TypeDefinition",
}
_EMPTY = ua.ReferenceDescription()


def node_class(aspace: Any, nodeid: ua.NodeId) -> ua.NodeClass | None:
    """The NodeClass of a node of ``aspace`` (asyncua's AddressSpace), None if there is no such node."""
    data = aspace.get(nodeid)
    if data is None:
        return None
    attribute = data.attributes.get(_A.NodeClass)
    value = attribute.value.Value.Value if attribute is not None and attribute.value is not None else None
    return ua.NodeClass(value) if value is not None else None


def reference_types(aspace: Any, reftype: ua.NodeId, subtypes: bool) -> frozenset[ua.NodeId] | None:
    """The reference types a request's ReferenceTypeId stands for: None for any (a null NodeId), else
    the type and, with ``subtypes``, every subtype of it. ServiceError(Bad_ReferenceTypeIdInvalid) when
    it names no ReferenceType."""
    if reftype.is_null():
        return None
    if node_class(aspace, reftype) != ua.NodeClass.ReferenceType:
        raise ServiceError(_SC.BadReferenceTypeIdInvalid)
    found = {reftype}
    if subtypes:
        pending = [reftype]
        while pending:
            data = aspace.get(pending.pop())
            for ref in data.references if data is not None else ():
                if ref.IsForward and ref.ReferenceTypeId == _HAS_SUBTYPE and ref.NodeId not in found:
                    found.add(ref.NodeId)
                    pending.append(ref.NodeId)
    return frozenset(found)


def shaped(ref: ua.ReferenceDescription, mask: int) -> ua.ReferenceDescription:
    """``ref`` with the fields ``mask`` (a BrowseResultMask) does not ask for left at their defaults."""
    if mask & _ALL_FIELDS == _ALL_FIELDS:
        return ref
    left_out = {name: getattr(_EMPTY, name) for bit, name in _MASKED_FIELDS.items() if not mask & bit}
    return dataclasses.replace(ref, **left_out)


def _result(code: int) -> ua.BrowseResult:
    result = ua.BrowseResult()
    result.StatusCode = ua.StatusCode(code)
    return result


# what a request's reference type stands for: the types (None: any), or why it is refused (a status code)
_Types = frozenset[ua.NodeId] | int | None


@dataclass(slots=True)
class _Rest:
    """What a continuation point holds: the references still to send, and how many go in one answer."""

    references: list[ua.ReferenceDescription]
    per_answer: int


class StandardViews:
    """The View services of one session."""

    # what the mixin finds on asyncua's InternalSession
    iserver: Any

    def _continuation_points(self) -> dict[bytes, _Rest]:
        points: dict[bytes, _Rest] | None = door.tagged(self, "browse_points")
        if points is None:
            points = {}
            door.tag(self, "browse_points", points)
            door.tag(self, "browse_point_ids", itertools.count(1))
        return points

    async def browse(self, params: ua.BrowseParameters) -> list[ua.BrowseResult]:
        aspace = self.iserver.aspace
        view = params.View.ViewId
        if not view.is_null() and node_class(aspace, view) != ua.NodeClass.View:
            raise ServiceError(_SC.BadViewIdUnknown)
        per_answer = int(params.RequestedMaxReferencesPerNode)
        known: dict[tuple[ua.NodeId, bool], _Types] = {}  # the request's types
        return [self._browse_one(aspace, d, per_answer, known) for d in params.NodesToBrowse]

    def _browse_one(
        self,
        aspace: Any,
        description: ua.BrowseDescription,
        per_answer: int,
        known: dict[tuple[ua.NodeId, bool], _Types],
    ) -> ua.BrowseResult:
        data = aspace.get(description.NodeId)
        if data is None:
            return _result(_SC.BadNodeIdUnknown)
        direction = description.BrowseDirection
        if direction not in _DIRECTIONS:
            return _result(_SC.BadBrowseDirectionInvalid)
        key = (description.ReferenceTypeId, bool(description.IncludeSubtypes))
        if key not in known:  # many descriptions of one request name the same reference type
            try:
                known[key] = reference_types(aspace, *key)
            except ServiceError as refused:
                known[key] = int(refused.code)
        types = known[key]
        if isinstance(types, int):
            return _result(types)
        forward = direction == ua.BrowseDirection.Forward
        both = direction == ua.BrowseDirection.Both
        classes = int(description.NodeClassMask)
        mask = int(description.ResultMask)
        found = [
            shaped(ref, mask)
            for ref in data.references
            if (both or ref.IsForward == forward)
            and (types is None or ref.ReferenceTypeId in types)
            and (not classes or classes & int(ref.NodeClass))
        ]
        return self._answer(found, per_answer)

    def _answer(self, references: list[ua.ReferenceDescription], per_answer: int) -> ua.BrowseResult:
        """A result of at most ``per_answer`` references, with a continuation point for the rest."""
        result = ua.BrowseResult()
        if per_answer <= 0 or len(references) <= per_answer:
            result.References = references
            return result
        points = self._continuation_points()
        if len(points) >= MAX_BROWSE_CONTINUATION_POINTS:
            return _result(_SC.BadNoContinuationPoints)
        point = next(door.tagged(self, "browse_point_ids")).to_bytes(8, "little")
        points[point] = _Rest(references[per_answer:], per_answer)
        result.References = references[:per_answer]
        result.ContinuationPoint = point
        return result

    async def browse_next(self, params: ua.BrowseNextParameters) -> ua.BrowseNextResult:
        points = self._continuation_points()
        answer = ua.BrowseNextResult()
        for point in params.ContinuationPoints:
            rest = points.pop(point or b"", None)
            if rest is None:
                answer.Results.append(_result(_SC.BadContinuationPointInvalid))
            elif params.ReleaseContinuationPoints:
                answer.Results.append(ua.BrowseResult())
            else:
                answer.Results.append(self._answer(rest.references, rest.per_answer))
        return answer

    async def translate_browsepaths_to_nodeids(self, paths: list[ua.BrowsePath]) -> list[ua.BrowsePathResult]:
        aspace = self.iserver.aspace
        return [_translate(aspace, path) for path in paths]


_NO_REMAINING_PATH = 0xFFFFFFFF  # RemainingPathIndex of a target the path ends at (OPC 10000-4 5.9.4.2)


def _translate(aspace: Any, path: ua.BrowsePath) -> ua.BrowsePathResult:
    result = ua.BrowsePathResult()
    elements = path.RelativePath.Elements or []
    if not elements:
        result.StatusCode = ua.StatusCode(_SC.BadNothingToDo)
        return result
    # only the last element may leave its TargetName empty (every target of its references)
    if any(not element.TargetName.Name for element in elements[:-1]):
        result.StatusCode = ua.StatusCode(_SC.BadBrowseNameInvalid)
        return result
    if aspace.get(path.StartingNode) is None:
        result.StatusCode = ua.StatusCode(_SC.BadNodeIdUnknown)
        return result
    current = [path.StartingNode]
    for element in elements:
        try:
            types = reference_types(aspace, element.ReferenceTypeId, element.IncludeSubtypes)
        except ServiceError:
            types = frozenset()  # a reference type that does not exist leads nowhere
        name = element.TargetName if element.TargetName.Name else None
        reached: dict[ua.NodeId, None] = {}
        for nodeid in current:
            data = aspace.get(nodeid)
            for ref in data.references if data is not None else ():
                if (
                    ref.IsForward != element.IsInverse
                    and (types is None or ref.ReferenceTypeId in types)
                    and (name is None or ref.BrowseName == name)
                ):
                    reached[ref.NodeId] = None
        if not reached:
            result.StatusCode = ua.StatusCode(_SC.BadNoMatch)
            return result
        current = list(reached)
    result.Targets = [ua.BrowsePathTarget(TargetId=nodeid, RemainingPathIndex=_NO_REMAINING_PATH) for nodeid in current]
    return result
