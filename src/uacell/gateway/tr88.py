"""The ISA-TR88 state graph a PLC walks, as uacell's machines can walk it after the PLC: pure.

Each state's steps are the commands taken there (uacell's method names, the acting state each
enters) and, for an acting state, its completion (``COMPLETE``, the state it ends in). Typed here
(decision 43): the NodeSet's HasCause references name the method of each transition but lead
MachineState.Reset to Running, not to the Resetting inside it, and do not say where an acting state
ends. ``path`` finds the fewest steps from the state uacell's machines show to the one the PLC
reports, so that a unit follows a PLC that moved several states between two reads, or that was
already running when uacell started.
"""

from __future__ import annotations

from collections import deque

COMPLETE = "complete"  # the step that ends an acting state

_STOP_ABORT = (("Stop", "Stopping"), ("Abort", "Aborting"))
STEPS: dict[str, tuple[tuple[str, str], ...]] = {
    "Stopped": (("Reset", "Resetting"), ("Abort", "Aborting")),
    "Resetting": ((COMPLETE, "Idle"), *_STOP_ABORT),
    "Idle": (("Start", "Starting"), *_STOP_ABORT),
    "Starting": ((COMPLETE, "Execute"), ("Hold", "Holding"), *_STOP_ABORT),
    "Execute": (("Hold", "Holding"), ("Suspend", "Suspending"), ("ToComplete", "Completing"), *_STOP_ABORT),
    "Holding": ((COMPLETE, "Held"), *_STOP_ABORT),
    "Held": (("Unhold", "Unholding"), *_STOP_ABORT),
    "Unholding": ((COMPLETE, "Execute"), ("Hold", "Holding"), *_STOP_ABORT),
    "Suspending": ((COMPLETE, "Suspended"), ("Hold", "Holding"), *_STOP_ABORT),
    "Suspended": (("Unsuspend", "Unsuspending"), ("Hold", "Holding"), *_STOP_ABORT),
    "Unsuspending": ((COMPLETE, "Execute"), ("Hold", "Holding"), *_STOP_ABORT),
    "Completing": ((COMPLETE, "Complete"), *_STOP_ABORT),
    "Complete": (("Reset", "Resetting"), *_STOP_ABORT),
    "Stopping": ((COMPLETE, "Stopped"), ("Abort", "Aborting")),
    "Aborting": ((COMPLETE, "Aborted"),),
    "Aborted": (("Clear", "Clearing"),),
    "Clearing": ((COMPLETE, "Stopped"), ("Abort", "Aborting")),
}


def path(current: str, target: str) -> list[tuple[str, str]]:
    """The fewest steps (action, the state it leads to) from ``current`` to ``target``; [] when they
    are the same state or either is not a TR88 state."""
    if current == target or current not in STEPS or target not in STEPS:
        return []
    came: dict[str, tuple[str, tuple[str, str]]] = {}
    queue = deque([current])
    while queue:
        state = queue.popleft()
        for step in STEPS[state]:
            following = step[1]
            if following in came or following == current:
                continue
            came[following] = (state, step)
            if following == target:
                steps = []
                while following != current:
                    before, taken = came[following]
                    steps.append(taken)
                    following = before
                return steps[::-1]
            queue.append(following)
    return []
