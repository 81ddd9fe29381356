"""uacell's benchmark suite: ``python -m benchmarks`` (``make bench``), ``--quick`` for a short run.

It starts every peer itself (uacell, a bare asyncua echo server, a bare node-opcua echo server) and
drives them with the node-opcua client of ``interop/bench_client.js`` in its own process. Machines
are shared and noisy, so every comparison is measured side by side: each round runs every peer once,
in an order that rotates from round to round, and a ratio is the median of the per-round ratios.
It prints one table (measure, uacell, reference, ratio, target, PASS/FAIL) and writes every raw
figure as JSON (``--json``). A FAIL is reported, never an error: the exit status is 0 unless the suite
itself broke. docs/performance.md explains each figure.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from benchmarks.gateway import gateway_section
from benchmarks.harness import (
    CLIENT,
    ECHO,
    FILLER,
    INTEROP,
    LOAD_CYCLE,
    READ_STATE,
    ROOT,
    SET_SPEED,
    STATE,
    TASK_CONTROL,
    TC_STATE,
    Peer,
    Peers,
    Report,
    client,
    fmt,
    loaded,
    median,
    rotated,
    running,
)
from benchmarks.history import history_section
from benchmarks.plant import plant_section
from benchmarks.robots import robots_section
from benchmarks.soak import soak_section
from benchmarks.sparkplug import sparkplug_section
from benchmarks.web import web_section


# --- sections ----------------------------------------------------------------------------------------
def calls_section(report: Report, peers: Peers, args: argparse.Namespace) -> None:
    """1a: SetMachSpeed and the LoadByName/UnloadProgram cycle against both echo servers; PackML Start."""
    print("== method calls (demo cell vs asyncua echo vs node-opcua echo)", flush=True)
    raw: dict[str, Any] = {}
    report.raw["calls"] = raw
    uac, asy, nod = peers.uacell(), peers.asyncua(), peers.node()
    targets = {uac.name: SET_SPEED, asy.name: ECHO, nod.name: ECHO}
    with running(uac, asy, nod):
        for n in args.sessions:
            for r in range(args.rounds):
                for p in rotated([uac, asy, nod], r):
                    spec = {"mode": "calls", "sessions": n, "seconds": args.seconds, "steps": targets[p.name]}
                    raw.setdefault(f"{p.name} x{n}", []).append(client(p.endpoint, spec))
            ours = raw[f"{uac.name} x{n}"]
            value = f"{median([x['rate'] for x in ours]):.0f}/s p50 {median([x['p50_ms'] for x in ours]):.1f} ms"
            value += f" p99 {median([x['p99_ms'] for x in ours]):.1f} ms"
            for ref, floor in ((asy, 1.2), (nod, 1.0)):
                theirs = raw[f"{ref.name} x{n}"]
                reference = f"{ref.name} {median([x['rate'] for x in theirs]):.0f}/s"
                reference += f" p50 {median([x['p50_ms'] for x in theirs]):.1f} ms"
                target = f">= {floor}x" if floor is not None else ""
                ok = (lambda x, f=floor: x >= f) if floor is not None else None
                ratio = median([a["rate"] / b["rate"] for a, b in zip(raw[f"{uac.name} x{n}"], theirs, strict=True)])
                report.add(f"SetMachSpeed calls/s, {n} session(s)", value, reference, ratio, target, ok)
            if n > 1:  # per-connection fairness: the slowest session's share against an even share
                for p in (uac, asy, nod):
                    runs = raw[f"{p.name} x{n}"]
                    shares = [min(x["per_session"]) * n / max(1, sum(x["per_session"])) for x in runs]
                    value = f"slowest session {median(shares):.2f} of an even share"
                    report.add(f"{p.name}: fairness, {n} sessions", value, "1.00 (even)", median(shares))
            errors = sum(x["errors"] for x in ours)
            if errors:
                print(f"  ! {errors} SetMachSpeed calls failed: {ours[0].get('first_error')}")
        # The cycle: one task control, so one session (a second session's LoadByName would be refused).
        for r in range(args.rounds):
            for p in rotated([uac, asy], r):
                steps = LOAD_CYCLE if p is uac else ECHO
                spec = {"mode": "calls", "sessions": 1, "seconds": args.seconds, "steps": steps}
                raw.setdefault(f"{p.name} cycle", []).append(client(p.endpoint, spec))
            raw.setdefault("start", []).append(
                client(uac.endpoint, {"mode": "start", "object": FILLER, "parameters": 5, "seconds": args.seconds})
            )
        ours, theirs = raw[f"{uac.name} cycle"], raw[f"{asy.name} cycle"]
        ratios = [a["rate"] / b["rate"] for a, b in zip(ours, theirs, strict=True)]
        report.add(
            "LoadByName+UnloadProgram calls/s, 1 session",
            f"{median([x['rate'] for x in ours]):.0f}/s p99 {median([x['p99_ms'] for x in ours]):.1f} ms",
            f"{asy.name} {median([x['rate'] for x in theirs]):.0f}/s",
            median(ratios),
            ">= 1.0x",
            lambda x: x >= 1.0,
        )
        if sum(x["errors"] for x in ours):
            print(f"  ! cycle calls failed: {ours[0].get('first_error')}")
        start = raw["start"]
        echo_p50 = median([x["p50_ms"] for x in theirs])
        start_p50 = median([x["p50_ms"] for x in start])
        report.add(
            "PackML Start (5 parameters) latency, 1 session",
            f"p50 {start_p50:.1f} ms p99 {median([x['p99_ms'] for x in start]):.1f} ms",
            f"{asy.name} p50 {echo_p50:.1f} ms",
            echo_p50 / start_p50 if echo_p50 and start_p50 else None,
        )


def large_cell_section(report: Report, peers: Peers, args: argparse.Namespace) -> None:
    """1b: SetMachSpeed on the large cell, as a ratio to the demo cell."""
    print("== cell size (100 PackML units and 10 robots vs the demo cell)", flush=True)
    raw: dict[str, Any] = {}
    report.raw["cell_size"] = raw
    demo, large = peers.uacell("demo"), peers.uacell("large")
    with running(demo, large):
        for n in args.size_sessions:
            for r in range(args.rounds):
                for p in rotated([demo, large], r):
                    spec = {"mode": "calls", "sessions": n, "seconds": args.seconds, "steps": SET_SPEED}
                    raw.setdefault(f"{p.name} x{n}", []).append(loaded(p, spec))
            ours, theirs = raw[f"{large.name} x{n}"], raw[f"{demo.name} x{n}"]
            report.add_rates(f"SetMachSpeed calls/s on the large cell, {n} session(s)", ours, theirs, "demo cell", 0.95)
            report.add_cpu(f"SetMachSpeed CPU per call on the large cell, {n} session(s)", ours, theirs, "demo cell")


def startup_section(report: Report, peers: Peers, args: argparse.Namespace) -> None:
    """1c and 3: start-up time (spawn to listening) and RSS after start-up."""
    print("== start-up and memory", flush=True)
    raw: dict[str, list[dict[str, float]]] = {}
    report.raw["startup"] = raw
    makers: list[tuple[str, Callable[[], Peer]]] = [
        ("demo", lambda: peers.uacell("demo")),
        ("demo, first start", lambda: peers.uacell("demo", snapshot=False)),
        ("large", lambda: peers.uacell("large")),
        ("units", lambda: peers.uacell("units")),
        ("asyncua", lambda: peers.asyncua(False)),
        ("asyncua+nodesets", lambda: peers.asyncua(True)),
        ("node-opcua+nodesets", lambda: peers.node(True)),
    ]
    for r in range(args.startup_rounds):
        for key, make in rotated(makers, r):
            peer = make()
            with running(peer):
                time.sleep(1.0)  # let start-up work finish before reading RSS
                raw.setdefault(key, []).append({"seconds": peer.startup, "rss_kib": peer.rss_kib()})
            print(f"  {key}: {peer.startup:.2f} s, {raw[key][-1]['rss_kib'] // 1024} MiB", flush=True)

    def t(key: str) -> float:
        return median([x["seconds"] for x in raw[key]]) or 0.0

    def m(key: str) -> float:
        return (median([x["rss_kib"] for x in raw[key]]) or 0.0) / 1024

    def ratio(a: str, b: str, what: str = "seconds") -> float | None:
        return median([x[what] / y[what] for x, y in zip(raw[a], raw[b], strict=True)])

    demo = f"{t('demo'):.2f} s, {m('demo'):.0f} MiB"
    for ref in ("asyncua", "asyncua+nodesets", "node-opcua+nodesets"):
        ok = (lambda x: x <= 0.3) if ref == "asyncua" else None
        report.add(
            "start-up, demo cell (restart)",
            demo,
            f"{ref} {t(ref):.2f} s",
            ratio("demo", ref),
            "<= 0.3x" if ok else "",
            ok,
        )
    first = "demo, first start"
    for ref in ("asyncua", "asyncua+nodesets"):
        ok = (lambda x: x <= 0.6) if ref == "asyncua" else None
        report.add(
            "start-up, demo cell, first start (no snapshot yet)",
            f"{t(first):.2f} s, {m(first):.0f} MiB",
            f"{ref} {t(ref):.2f} s",
            ratio(first, ref),
            "<= 0.6x" if ok else "",
            ok,
        )
    for ref in ("asyncua", "asyncua+nodesets", "node-opcua+nodesets"):
        report.add("RSS, demo cell", f"{m('demo'):.0f} MiB", f"{ref} {m(ref):.0f} MiB", ratio("demo", ref, "rss_kib"))
    report.add(
        "start-up, large cell",
        f"{t('large'):.2f} s, {m('large'):.0f} MiB",
        f"demo cell {t('demo'):.2f} s",
        ratio("large", "demo"),
        "<= 1.5x",
        lambda x: x <= 1.5,
    )
    from benchmarks.cells import SIZES

    units = SIZES["units"][0]
    large_units, large_robots, _ = SIZES["large"]
    per_unit = (m("units") - m("demo")) / (units - 1)
    per_robot = (m("large") - m("demo") - per_unit * (large_units - 1)) / (large_robots - 1)
    report.add("RSS per added PackML unit", f"{per_unit:.2f} MiB", "2 MiB", per_unit / 2.0, "<= 1x", lambda x: x <= 1)
    report.add("RSS per added robot (2 task controls)", f"{per_robot:.2f} MiB", "", None)
    raw["per_unit_mib"] = per_unit  # type: ignore[assignment]
    raw["per_robot_mib"] = per_robot  # type: ignore[assignment]


def notify_section(report: Report, peers: Peers, args: argparse.Namespace) -> None:
    """1d: from a call's return to the data change of CurrentState and to the TransitionEvent."""
    print("== state-change notification latency (LoadByName/UnloadProgram on TaskControl1)", flush=True)
    raw: dict[str, Any] = {}
    report.raw["notify"] = raw
    with running(peers.uacell()) as (uac,):
        for r in range(args.rounds):
            for interval in rotated([0, 50], r):
                spec = {
                    "mode": "notify",
                    "interval": interval,
                    "seconds": args.seconds,
                    "object": TASK_CONTROL,
                    "current": TC_STATE,
                    "steps": LOAD_CYCLE,
                }
                raw.setdefault(str(interval), []).append(client(uac.endpoint, spec))
    for interval in (0, 50):
        runs = raw[str(interval)]
        for what, name in (("value", "CurrentState data change"), ("event", "TransitionEvent")):
            p50 = median([x[what]["p50_ms"] for x in runs])
            p99 = median([x[what]["p99_ms"] for x in runs])
            limit = interval + 5
            report.add(
                f"{name} latency, {interval} ms publishing",
                f"p50 {fmt(p50, ' ms')} p99 {fmt(p99, ' ms')}",
                f"{limit} ms",
                max(p50, 0.0) / limit if p50 is not None else None,  # < 0: it arrived before the response
                "<= 1x (p50)",
                lambda x: x <= 1.0,
            )
        missed = sum(x["missed"] for x in runs)
        if missed:
            print(f"  ! {missed} notifications did not arrive within 2 s ({interval} ms)")


def sessions_section(report: Report, peers: Peers, args: argparse.Namespace) -> None:
    """1e: many sessions, each subscribed to a state; a Read and a SetMachSpeed from one more client."""
    # asyncua activates at most 1,000 sessions (InternalSession.max_connections): the probing client
    # is the last of ``total``.
    total = args.many_sessions - 1
    procs_n = max(1, min(4, total // 100))
    print(f"== {total} concurrent sessions from {procs_n} client processes, and one probing", flush=True)
    raw: dict[str, Any] = {}
    report.raw["sessions"] = raw
    with running(peers.uacell()) as (uac,):
        time.sleep(1.0)
        before = uac.rss_kib()
        holders = []
        share = [total // procs_n + (1 if i < total % procs_n else 0) for i in range(procs_n)]
        for n in share:
            spec = {"mode": "hold", "sessions": n, "current": STATE}
            holders.append(
                subprocess.Popen(
                    ["node", str(CLIENT), uac.endpoint, json.dumps(spec)],
                    cwd=INTEROP,
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.DEVNULL,
                    text=True,
                )
            )
        ready = 0
        try:
            for h in holders:
                assert h.stdout is not None
                for line in h.stdout:  # node-opcua may print warnings before the JSON line
                    if line.startswith('{"ready"'):
                        ready += json.loads(line)["ready"]
                        break
            after = uac.rss_kib()
            one = {"mode": "calls", "sessions": 1, "seconds": args.seconds}
            probe: dict[str, Any] = {}
            for key, steps in (("read", READ_STATE), ("call", SET_SPEED)):
                try:
                    probe[key] = client(uac.endpoint, one | {"steps": steps})
                except RuntimeError as err:  # one more client could not get in: reported as such
                    probe[key] = {"error": str(err)}
                    print(f"  ! the probing client failed: {err}", flush=True)
        finally:
            results = []
            for h in holders:
                try:
                    out, _ = h.communicate("stop\n", timeout=120)
                    lines = [ln for ln in out.splitlines() if ln.strip()]
                    results.append(json.loads(lines[-1]) if lines else {})
                except (subprocess.TimeoutExpired, json.JSONDecodeError):
                    h.kill()
                    h.wait()
                    results.append({})
    alive = sum(r.get("alive", 0) for r in results)
    raw.update(
        {"requested": total, "ready": ready, "alive": alive, "holders": results, "rss_before_kib": before}
        | {"rss_after_kib": after, "probe": probe}
    )
    per_session = (after - before) / max(1, ready)
    report.add(
        "sessions held (subscribed, publishing)",
        f"{alive}",
        f"{total}",
        alive / total,
        ">= 1x",
        lambda x: x >= 1.0,
    )
    report.add(f"RSS per session ({ready} sessions)", f"{per_session:.0f} KiB", "", None)
    read, call = probe["read"], probe["call"]
    report.add(
        f"Read p99 with {ready} sessions",
        f"p50 {read['p50_ms']:.1f} ms p99 {read['p99_ms']:.1f} ms" if "error" not in read else "no connection",
        "20 ms",
        read["p99_ms"] / 20.0 if "error" not in read else float("inf"),
        "<= 1x",
        lambda x: x <= 1.0,
    )
    report.add(
        f"SetMachSpeed p99 with {ready} sessions",
        f"p50 {call['p50_ms']:.1f} ms p99 {call['p99_ms']:.1f} ms" if "error" not in call else "no connection",
        "20 ms",
        call["p99_ms"] / 20.0 if "error" not in call else float("inf"),
        "<= 1x",
        lambda x: x <= 1.0,
    )


SECTIONS = {
    "calls": calls_section,
    "size": large_cell_section,
    "notify": notify_section,
    "startup": startup_section,
    "sessions": sessions_section,
    "web": web_section,
    "history": history_section,
    "plant": plant_section,
    "sparkplug": sparkplug_section,
    "gateway": gateway_section,
    "soak": soak_section,
    "robots": robots_section,
}


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one round, short runs, 100 sessions (a few minutes)")
    parser.add_argument("--rounds", type=int, help="interleaved rounds (default 3, quick 1)")
    parser.add_argument("--seconds", type=float, help="length of each measured load run (default 2, quick 1.5)")
    parser.add_argument("--sessions-total", type=int, dest="many_sessions", help="concurrent sessions (1000/100)")
    parser.add_argument("--cells", type=int, help="uacell processes of the plant and sparkplug sections (20/5)")
    parser.add_argument("--minutes", type=float, help="length of the soak section (default 20, quick 5)")
    parser.add_argument("--only", choices=sorted(SECTIONS), action="append", help="run only these sections")
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "last-run.json", help="raw figures")
    args = parser.parse_args()
    # Three: a ratio is the median of the rounds' ratios, and of two rounds that is their mean, which
    # one slow round of a shared machine decides.
    args.rounds = args.rounds or (1 if args.quick else 3)
    args.seconds = args.seconds or (1.5 if args.quick else 2.0)
    args.many_sessions = args.many_sessions or (100 if args.quick else 1000)
    args.cells = args.cells or (5 if args.quick else 20)
    args.minutes = args.minutes or (5.0 if args.quick else 20.0)
    args.startup_rounds = max(1, args.rounds - 1)  # the large cell alone takes a minute to start here
    args.sessions = (1, 8, 32)
    args.size_sessions = (1, 8, 32)
    report = Report()
    report.raw["meta"] = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "host": platform.node(),
        "cpus": os.cpu_count(),
        "load_average": os.getloadavg(),
        "python": platform.python_version(),
        "arguments": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
    }
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="uacell-bench-") as tmp:
        peers = Peers(Path(tmp))
        for name, section in SECTIONS.items():
            if args.only and name not in args.only:
                continue
            started = time.monotonic()
            try:
                section(report, peers, args)
            except Exception as err:  # a broken section is reported, the others still run
                print(f"  ! section {name} failed: {err}", flush=True)
                report.raw.setdefault("errors", {})[name] = str(err)
            report.raw["meta"].setdefault("section_seconds", {})[name] = round(time.monotonic() - started, 1)
    report.raw["meta"]["seconds"] = round(time.monotonic() - t0, 1)
    report.raw["meta"]["load_average_after"] = os.getloadavg()
    report.raw["rows"] = [r.__dict__ for r in report.rows]
    report.print()
    args.json.write_text(json.dumps(report.raw, indent=1, default=str) + "\n")
    print(f"raw figures: {args.json} (run took {report.raw['meta']['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
