"""The ``uacell`` command: serve, models, user."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import errno
import logging
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from uacell import __version__, _entry
from uacell.config import Config, load_config, load_factory
from uacell.errors import ConfigError
from uacell.logs import install_repeat_filter
from uacell.models import ModelError, fetch_models, locate_models, models_dir

if TYPE_CHECKING:
    from uacell.config import Config
    from uacell.server import UacellServer
    from uacell.web.server import RunningWeb

log = logging.getLogger("uacell")
STOP_GRACE = 3.0  # seconds a stop request waits for the server to close in order (SIGTERM: gone within 5 s)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="uacell", description="OPC UA server for robot cells and packaging units")
    p.add_argument("--version", action="version", version=f"uacell {__version__}")
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    sub = p.add_subparsers(dest="command", required=True)

    serve = sub.add_parser("serve", help="serve the configured cell (the demo cell by default)")
    serve.add_argument("--config", type=Path, help="TOML configuration file")
    serve.add_argument("--host", help="address to listen on (default 127.0.0.1)")
    serve.add_argument("--port", type=int, help="TCP port (default 4840)")
    serve.add_argument("--data-dir", type=Path, help="data directory (default: per-user data directory)")
    serve.add_argument("--models-dir", help="directory holding the official NodeSet files")
    serve.add_argument("--web-host", help="address of the web HMI (default 127.0.0.1)")
    serve.add_argument("--web-port", type=int, help="port of the web HMI (default 8080, 0: any free port)")
    serve.add_argument("--no-web", action="store_true", help="do not run the web HMI beside the server")

    web = sub.add_parser("web", help="run the web HMI for an OPC UA server")
    web.add_argument("--server", required=True, help="the server's endpoint, e.g. opc.tcp://HOST:4840/")
    web.add_argument("--config", type=Path, help="TOML configuration file (its [web] section)")
    web.add_argument("--host", help="address to listen on (default 127.0.0.1; any other: HTTPS only)")
    web.add_argument("--port", type=int, help="TCP port (default 8080, 0: any free port)")
    web.add_argument("--data-dir", type=Path, help="data directory (holds the HMI's certificate)")

    models = sub.add_parser("models", help="the official NodeSet files")
    msub = models.add_subparsers(dest="action", required=True)
    fetch = msub.add_parser("fetch", help="download and verify them into the per-user cache")
    fetch.add_argument("--force", action="store_true", help="fetch again even if the cache is complete")
    path = msub.add_parser("path", help="print the directory uacell reads them from")
    path.add_argument("--models-dir", help="check this directory instead")

    conf = sub.add_parser("config", help="the configuration file")
    confsub = conf.add_subparsers(dest="action", required=True)
    check = confsub.add_parser("check", help="validate a configuration and print the cell it would serve")
    check.add_argument("file", nargs="?", type=Path, help="TOML configuration file (default: none, the demo cell)")

    user = sub.add_parser("user", help="manage the users who may log in")
    user.add_argument("--config", type=Path, help="TOML configuration file (for its data directory)")
    user.add_argument("--data-dir", type=Path, help="data directory")
    usub = user.add_subparsers(dest="action", required=True)
    add = usub.add_parser("add", help="add a user or change an existing user's role and password")
    add.add_argument("name")
    add.add_argument("--role", required=True, choices=["observer", "operator", "engineer", "admin"])
    add.add_argument("--password-stdin", action="store_true", help="read the password from standard input")
    rm = usub.add_parser("remove", help="remove a user")
    rm.add_argument("name")
    usub.add_parser("list", help="list users and their roles")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    install_repeat_filter()  # a flood of identical errors must not fill the disk
    try:
        if args.command == "serve":
            return _serve(args)
        if args.command == "models":
            return _models(args)
        if args.command == "user":
            return _user(args)
        if args.command == "web":
            return _web(args)
        if args.command == "config":
            from uacell.config_check import run_check

            return run_check(args.file)
    except (ConfigError, ModelError) as exc:
        print(f"uacell: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 2


def _models(args: argparse.Namespace) -> int:
    if args.action == "fetch":
        print(fetch_models(force=args.force))
        return 0
    locate_models(args.models_dir)
    print(models_dir(args.models_dir))
    return 0


def _user(args: argparse.Namespace) -> int:
    from uacell.users import run_user_command

    config = load_config(args.config)
    data_dir = args.data_dir or config.server.data_dir
    return run_user_command(args, data_dir)


def _serve(args: argparse.Namespace) -> int:
    # Until the event loop takes over, a stop request ends start-up quietly (exit 0, no traceback);
    # `uacell` and `python -m uacell` install the handler first thing (uacell._entry), main() here
    # for callers that enter through it.
    _entry.install_early_stop()
    try:
        return _prepare_and_run(args)
    except BaseException:
        if _entry.stop_requested:
            return 0
        raise


def _prepare_and_run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    if args.host:
        config.server.host = args.host
    if args.port is not None:
        config.server.port = args.port
    if args.data_dir:
        config.server.data_dir = args.data_dir
    if args.models_dir:
        config.server.models_dir = args.models_dir
    if args.web_host:
        config.web.host = args.web_host
    if args.web_port is not None:
        config.web.port = args.web_port
    if args.no_web:
        config.web.enabled = False
    locate_models(config.server.models_dir)  # fail early, with the fix, before any other work
    from uacell.config_check import equipment_specs

    for where, spec in equipment_specs(config):
        load_factory(spec, where)  # importable and callable, before any other work
    try:
        config.server.data_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create data directory {config.server.data_dir}: {exc.strerror or exc}") from exc
    return asyncio.run(_run(config))


async def _run(config: Config) -> int:
    from uacell.server import UacellServer

    app = UacellServer(config)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await app.setup()
    except BaseException:
        # e.g. an equipment factory failed: close what was already made (drivers connected) first.
        with contextlib.suppress(Exception):
            await app.stop()
        raise
    if stop.is_set():  # asked to stop while setting up: never start listening
        log.info("shutting down")
        with contextlib.suppress(Exception):
            await app.stop()
        return 0
    # asyncua logs a traceback of its own when it cannot bind; uacell says it in one line instead.
    server_log = logging.getLogger("asyncua.server.server")
    level = server_log.level
    server_log.setLevel(logging.CRITICAL)
    try:
        await app.start()
    except OSError as exc:
        reason = "address already in use" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
        print(f"uacell: cannot listen on {config.server.host}:{config.server.port}: {reason}", file=sys.stderr)
        with contextlib.suppress(Exception):
            await app.stop()
        return 2
    finally:
        server_log.setLevel(level)
    print(f"uacell listening on {app.endpoint}", flush=True)
    web = None
    if config.web.enabled:
        try:
            web = await _start_web_beside(config, app)
        except ConfigError as exc:
            print(f"uacell: {exc}", file=sys.stderr)
            with contextlib.suppress(Exception):
                await app.stop()
            return 2
        print(f"uacell web on {web.url}", flush=True)
    await stop.wait()
    log.info("shutting down")
    try:
        # Calls under way get a moment to finish; whatever still runs after it is cancelled.
        async with asyncio.timeout(STOP_GRACE):
            if web is not None:
                await web.stop()
            await app.stop()
    except TimeoutError:
        log.warning("shutdown took longer than %.0f s: stopping without waiting further", STOP_GRACE)
    return 0


def _https_files(config: Config) -> tuple[Path | None, Path | None]:
    web = config.web
    return (
        Path(web.certificate).expanduser() if web.certificate else None,
        Path(web.private_key).expanduser() if web.private_key else None,
    )


async def _start_web_beside(config: Config, app: UacellServer) -> RunningWeb:
    """The web HMI beside the server: its certificate trusted here, HTTPS with the server's by default."""
    from uacell.pki import PkiPaths
    from uacell.roles import is_loopback
    from uacell.web.server import start_web, trust_hmi

    data_dir = config.server.data_dir
    trust_hmi(data_dir)
    pki = PkiPaths.in_data_dir(data_dir)
    cert, key = _https_files(config)
    if cert is None and key is None and not is_loopback(config.web.host):
        cert, key = pki.cert, pki.key
    host = config.server.host
    if host in ("0.0.0.0", "::", ""):
        host = "127.0.0.1"
    shown = f"[{host}]" if ":" in host else host
    return await start_web(
        f"opc.tcp://{shown}:{config.server.port}/",
        data_dir,
        host=config.web.host,
        port=config.web.port,
        server_certificate=pki.cert,
        https_certificate=cert,
        https_key=key,
    )


def _web(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    if args.host:
        config.web.host = args.host
    if args.port is not None:
        config.web.port = args.port
    data_dir = args.data_dir or config.server.data_dir
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create data directory {data_dir}: {exc.strerror or exc}") from exc
    return asyncio.run(_run_web(args.server, data_dir, config))


async def _run_web(server: str, data_dir: Path, config: Config) -> int:
    from uacell.web.server import start_web

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    cert, key = _https_files(config)
    try:
        web = await start_web(
            server, data_dir, host=config.web.host, port=config.web.port, https_certificate=cert, https_key=key
        )
    except ConfigError as exc:
        print(f"uacell: {exc}", file=sys.stderr)
        return 2
    print(f"uacell web on {web.url}", flush=True)
    await stop.wait()
    await web.stop()
    return 0
