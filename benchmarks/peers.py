"""The servers the suite measures, each started as its own process by ``python -m benchmarks.peers``.

- ``asyncua [--nodesets]``: a bare asyncua server with one echo method (``Objects/Bench/Echo``), optionally
  importing the same four NodeSets as uacell (asyncua's ``import_xml``);
- ``uacell --cell demo|large|units|FILE.toml``: uacell with the cell ``benchmarks.cells.bench_cell`` names
  (or a cell file),
  acting times zero (``--pubsub URL --publisher-id ID``: publishing to that broker; ``--history-events N``:
  N events stored with the Server object before it says ``listening``).

Each prints ``listening`` once clients can connect and runs until SIGTERM.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys

ECHO_NAMESPACE = "urn:uacell:bench"


async def _until_stopped() -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()


async def bare_asyncua(port: int, nodesets: bool) -> None:
    from asyncua import Server, ua

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    server = Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/")
    if nodesets:
        # asyncua's own importer; the files lose their DesignToolOnly nodes first, as in uacell
        # (asyncua cannot import them: their parents are not in the files)
        from uacell.catalog import companions
        from uacell.core.companion import models_of
        from uacell.models.source import locate_models, official_models
        from uacell.ua.nodesets import without_design_tool_only

        models = official_models(models_of(companions()))
        paths = locate_models(models)
        for model in models:
            await server.import_xml(xmlstring=without_design_tool_only(paths[model.key])[0])
    ns = await server.register_namespace(ECHO_NAMESPACE)
    bench = await server.nodes.objects.add_object(ua.NodeId("Bench", ns), ua.QualifiedName("Bench", ns))
    await bench.add_method(
        ua.NodeId("Echo", ns), ua.QualifiedName("Echo", ns), lambda parent, *args: list(args),
        [ua.VariantType.Variant], [ua.VariantType.Variant],
    )  # fmt: skip
    await server.start()
    print("listening", flush=True)
    await _until_stopped()
    await server.stop()


async def uacell(
    port: int,
    cell: str,
    data_dir: str,
    cache_dir: str,
    history: bool = True,
    pubsub: str = "",
    publisher_id: str = "",
    sparkplug: str = "",
    history_events: int = 0,
) -> None:
    from pathlib import Path

    from benchmarks.cells import bench_cell
    from uacell.config import Config
    from uacell.core import early
    from uacell.server import UacellServer

    logging.basicConfig(level=logging.ERROR)
    config = Config()
    config.server.port = port
    config.server.data_dir = Path(data_dir)
    config.server.cache_dir = Path(cache_dir) if cache_dir else None
    config.packml.acting_time = 0.0
    config.history.enabled = history
    # room for the sessions section's thousand subscribed sessions (as an operator would raise [limits])
    limits = config.limits
    limits.connections, limits.sessions, limits.subscriptions = 1100, 1050, 2100
    limits.pending_per_address = 1100  # they all come from 127.0.0.1, many at once
    if pubsub:  # publish to this broker as publisher_id
        config.pubsub.enabled = True
        config.pubsub.broker = pubsub
        config.pubsub.publisher_id = publisher_id
    if sparkplug:  # an edge node on this broker, named publisher_id
        config.sparkplug.enabled = True
        config.sparkplug.broker = sparkplug
        config.sparkplug.group_id = "bench"
        config.sparkplug.edge_node_id = publisher_id
    if cell.endswith(".toml"):  # a cell file (the gateway section's)
        from uacell.config import load_cell

        parts = load_cell(cell).parts()
    else:
        parts = bench_cell(cell)
    app = UacellServer(config, parts=parts)
    await app.setup()
    early.resume_gc()  # as `uacell serve` does
    await app.start()
    if history_events and app.history is not None:  # the history section's stall row
        from benchmarks.history import fill_events

        fill_events(app.history, history_events)
        await app.history.store.flush()
    print("listening", flush=True)
    await _until_stopped()
    await app.stop()


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.peers")
    parser.add_argument("kind", choices=("asyncua", "uacell"))
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--nodesets", action="store_true")
    parser.add_argument("--cell", default="demo")
    parser.add_argument("--data-dir", default="")
    parser.add_argument("--cache-dir", default="")
    parser.add_argument("--no-history", action="store_true", help="[history] enabled = false")
    parser.add_argument("--pubsub", default="", help="[pubsub] broker (enables PubSub)")
    parser.add_argument("--publisher-id", default="", help="[pubsub] publisher_id ([sparkplug] edge_node_id)")
    parser.add_argument("--sparkplug", default="", help="[sparkplug] broker (enables Sparkplug B)")
    parser.add_argument("--history-events", type=int, default=0, help="events stored with the Server object")
    args = parser.parse_args()
    if args.kind == "asyncua":
        asyncio.run(bare_asyncua(args.port, args.nodesets))
    else:
        from uacell.core import early
        from uacell.ua import codecache

        early.pause_gc()  # as `uacell serve` does, from its first line
        codecache.install()
        history = not args.no_history
        where = (args.port, args.cell, args.data_dir, args.cache_dir)
        early.run(uacell(*where, history, args.pubsub, args.publisher_id, args.sparkplug, args.history_events))
    return 0


if __name__ == "__main__":
    sys.exit(main())
