"""A lever measured side by side: ``python -m benchmarks.compare OTHER [--rounds 5] [--loads 1,8,32,cycle]``.

Runs two uacell peers in one run: this checkout's ("new") and the one in ``OTHER`` ("old": another
checkout of uacell, e.g. ``git worktree add --detach ../before HEAD~1``, its sources imported first),
or this checkout's again with ``--old-env NAME=VALUE`` set for the old peer only (``UACELL_EVENT_LOOP=asyncio``
compares the event loops). Each round runs every load (SetMachSpeed at N sessions, or ``cycle``:
LoadByName + UnloadProgram at one session) on both peers, in an order that rotates from round to
round; it prints each peer's calls/s per round and the median of the per-round ratios new/old, and
each peer's CPU time per call (the whole process, all threads; medians): the rate moves with what
else the machine does, the work a call costs much less.
docs/performance.md records the levers measured so.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

from benchmarks.harness import (
    LOAD_CYCLE,
    SET_SPEED,
    Peer,
    Peers,
    free_port,
    loaded,
    rotated,
    running,
)


def old_peer(new: Peer, tmp: Path, other: Path | None, env: list[str]) -> Peer:
    """``new``'s command for the old peer: its own port and directories, ``other``'s sources first."""
    cmd = list(new.cmd[: new.cmd.index("--data-dir")])
    port = free_port()
    cmd[cmd.index("--port") + 1] = str(port)
    prefix = ["env", *env]
    if other is not None:
        prefix.append(f"PYTHONPATH={other / 'src'}:{other}")
    cmd += ["--data-dir", str(tmp / "old"), "--cache-dir", str(tmp / "old-cache")]
    return Peer("old", [*prefix, *cmd], cwd=other or new.cwd, port=port)


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.compare", description=__doc__.split("\n")[0])
    parser.add_argument("other", nargs="?", type=Path, help="another uacell checkout (default: this one)")
    parser.add_argument("--old-env", action="append", default=[], metavar="NAME=VALUE", help="for the old peer")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--loads", default="1,8,32,cycle", help="session counts and/or 'cycle'")
    parser.add_argument("--cell", default="demo")
    args = parser.parse_args()
    if args.other is not None and not (args.other / "src" / "uacell").is_dir():
        parser.error(f"{args.other} is not a uacell checkout (no src/uacell)")
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    loads = [x.strip() for x in args.loads.split(",") if x.strip()]
    rates: dict[tuple[str, str], list[float]] = {}
    cpu: dict[tuple[str, str], list[float]] = {}  # microseconds of CPU per call
    with tempfile.TemporaryDirectory() as tmp:
        new = Peers(Path(tmp)).uacell(args.cell)
        new.name = "new"
        old = old_peer(new, Path(tmp), args.other.resolve() if args.other else None, args.old_env)
        with running(new, old):
            for r in range(args.rounds):
                for load in loads:
                    steps, sessions = (LOAD_CYCLE, 1) if load == "cycle" else (SET_SPEED, int(load))
                    for peer in rotated([new, old], r):
                        spec = {"mode": "calls", "sessions": sessions, "seconds": args.seconds, "steps": steps}
                        result = loaded(peer, spec)
                        cpu.setdefault((peer.name, load), []).append(result["cpu_us_per_call"])
                        if result.get("errors"):
                            print(f"  ! {peer.name} {load}: {result['errors']} failed: {result.get('first_error')}")
                        rates.setdefault((peer.name, load), []).append(result["rate"])
    # every round measured every load on both peers: each list below holds args.rounds (>= 1) figures
    for load in loads:
        ours, theirs = rates[("new", load)], rates[("old", load)]
        ratio = statistics.median([a / b for a, b in zip(ours, theirs, strict=True)])
        print(f"{load:>6}: new {[round(x) for x in ours]} old {[round(x) for x in theirs]} new/old {ratio:.3f}x")
        ours_cpu, theirs_cpu = statistics.median(cpu[("new", load)]), statistics.median(cpu[("old", load)])
        cpu_ratio = ours_cpu / theirs_cpu
        print(f"        CPU per call: new {ours_cpu:.0f} us, old {theirs_cpu:.0f} us, new/old {cpu_ratio:.3f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
