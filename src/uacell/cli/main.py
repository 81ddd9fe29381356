"""The ``uacell`` command: serve, web, health, models, user, cert.

Every subcommand takes the same configuration: ``--config FILE`` (or ``$UACELL_CONFIG``) and
``--data-dir DIR`` (or ``$UACELL_DATA_DIR``), so that ``uacell user ...`` and ``uacell cert ...`` act
on the service's data. These and the logging options are accepted before the subcommand and anywhere
after it. Every option is checked before anything is written.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import errno
import logging
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from uacell import __version__
from uacell.config import (
    LOG_FORMATS,
    LOG_LEVELS,
    ROLES,
    Config,
    check_directory,
    check_file,
    check_host,
    check_port,
    load_config,
    validate,
)
from uacell.core import early
from uacell.core.companion import models_of
from uacell.core.errors import ConfigError
from uacell.models import ModelError, ModelFile, fetch_models, locate_models, models_dir, official_models

if TYPE_CHECKING:
    from uacell.server import UacellServer
    from uacell.web.hosting import RunningWeb

log = logging.getLogger("uacell")
STOP_GRACE = 3.0  # seconds a stop waits for the server to close in order (besides [server] shutdown_delay)


def _port(text: str) -> int:
    try:
        return check_port(int(text), "port")
    except (ValueError, ConfigError) as exc:
        raise argparse.ArgumentTypeError(f"must be a TCP port 1..65535, not {text!r}") from exc


def _web_port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port 0..65535 (0: any free port), not {text!r}")
    return value


def _host(text: str) -> str:
    try:
        return check_host(text, "host")
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(f"must be an IP address or host name, not {text!r}") from exc


def _common() -> argparse.ArgumentParser:
    """Options every (sub)command accepts; SUPPRESS keeps a later parser from resetting an earlier value."""
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("configuration and logging (accepted anywhere)")
    s = argparse.SUPPRESS
    g.add_argument("--config", type=Path, default=s, help="TOML configuration file (default: $UACELL_CONFIG)")
    g.add_argument(
        "--data-dir",
        type=Path,
        default=s,
        help="data directory (default: $UACELL_DATA_DIR, the configuration's data_dir, or the per-user data directory)",
    )
    g.add_argument("--log-level", type=str.upper, choices=LOG_LEVELS, default=s, help="default INFO")
    g.add_argument("--log-format", choices=LOG_FORMATS, default=s, help="text (default) or json lines")
    g.add_argument("--log-file", type=Path, default=s, help="also log to this file, rotated")
    return p


def _parser() -> argparse.ArgumentParser:
    common = _common()
    p = argparse.ArgumentParser(
        prog="uacell", description="OPC UA server for robot cells and packaging units", parents=[common]
    )
    p.add_argument("--version", action="version", version=f"uacell {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    def leaf(parent: Any, name: str, help: str) -> argparse.ArgumentParser:
        parser: argparse.ArgumentParser = parent.add_parser(name, help=help, description=help, parents=[common])
        return parser

    serve = leaf(sub, "serve", "serve the configured cell (the demo cell by default)")
    serve.add_argument("--host", type=_host, help="address to listen on (default 127.0.0.1)")
    serve.add_argument("--port", type=_port, help="TCP port (default 4840)")
    serve.add_argument("--models-dir", help="directory holding the official NodeSet files")
    serve.add_argument("--web-host", type=_host, help="address of the web HMI (default 127.0.0.1)")
    serve.add_argument("--web-port", type=_web_port, help="port of the web HMI (default 8080, 0: any free port)")
    serve.add_argument("--no-web", action="store_true", help="do not run the web HMI beside the server")

    web = leaf(sub, "web", "run the web HMI for an OPC UA server")
    web.add_argument("--server", required=True, help="the server's endpoint, e.g. opc.tcp://HOST:4840/")
    web.add_argument("--host", type=_host, help="address to listen on (default 127.0.0.1; any other: HTTPS only)")
    web.add_argument("--port", type=_web_port, help="TCP port (default 8080, 0: any free port)")

    health = leaf(sub, "health", "exit 0 when the server answers and is Running (for health checks)")
    health.add_argument("--endpoint", help="default: opc.tcp://<configured host>:<port>/")
    health.add_argument("--timeout", type=float, default=10.0, help="seconds (default 10)")

    models = leaf(sub, "models", "the official NodeSet files")
    msub = models.add_subparsers(dest="action", required=True)
    fetch = leaf(msub, "fetch", "download and verify them into the per-user cache")
    fetch.add_argument("--force", action="store_true", help="fetch again even if the cache is complete")
    path = leaf(msub, "path", "print the directory uacell reads them from")
    path.add_argument("--models-dir", help="check this directory instead")

    nodeset = leaf(sub, "nodeset", "the served cell as a NodeSet2 file")
    nsub = nodeset.add_subparsers(dest="action", required=True)
    export = leaf(nsub, "export", "write the configured cell's instances as NodeSet2 XML, without serving")
    export.add_argument("-o", "--output", type=Path, help="file to write (default: standard output)")
    export.add_argument("--models-dir", help="directory holding the official NodeSet files")

    conf = sub.add_parser("config", help="the configuration file")
    confsub = conf.add_subparsers(dest="action", required=True)
    check = confsub.add_parser("check", help="validate a configuration and print the cell it would serve")
    check.add_argument("file", nargs="?", type=Path, help="TOML configuration file (default: none, the demo cell)")
    check.add_argument(
        "--connect", action="store_true", help="also try every PLC endpoint and tag the gateway drivers name"
    )

    user = leaf(sub, "user", "manage the users who may log in")
    usub = user.add_subparsers(dest="action", required=True)
    add = leaf(usub, "add", "add a new user (refused when the name exists)")
    add.add_argument("name")
    add.add_argument("--role", required=True, choices=ROLES)
    add.add_argument("--password-stdin", action="store_true", help="read the password from standard input")
    add.add_argument(
        "--certificate",
        type=Path,
        help="an X.509 certificate (DER or PEM) the user logs in with; no password is asked unless --password-stdin",
    )
    passwd = leaf(usub, "passwd", "set an existing user's password")
    passwd.add_argument("name")
    passwd.add_argument("--password-stdin", action="store_true", help="read the password from standard input")
    role = leaf(usub, "role", "change an existing user's role")
    role.add_argument("name")
    role.add_argument("role", choices=ROLES)
    ucert = leaf(usub, "certificate", "let an existing user log in with an X.509 certificate, or no longer")
    ucert.add_argument("name")
    ucert.add_argument(
        "certificate", help="the certificate file (DER or PEM); with --remove also its SHA-256 thumbprint"
    )
    ucert.add_argument("--remove", action="store_true", help="stop the user logging in with this certificate")
    rm = leaf(usub, "remove", "remove a user")
    rm.add_argument("name")
    leaf(usub, "list", "list users and their roles")

    cert = leaf(sub, "cert", "the server's certificate and the client certificates it trusts or rejected")
    csub = cert.add_subparsers(dest="action", required=True)
    leaf(csub, "list", "own, trusted, issuer and rejected certificates, and revocation lists")
    for name, text in (
        ("trust", "trust a client certificate (from rejected/ or a file)"),
        ("reject", "stop trusting a client certificate (moved to rejected/)"),
        ("remove", "delete a trusted, issuer or rejected certificate"),
    ):
        c = leaf(csub, name, text)
        c.add_argument("id", help="a thumbprint (or its first characters) or a certificate file")
    issuer = leaf(csub, "issuer", "add a CA certificate that completes client chains without being trusted itself")
    issuer.add_argument("file", help="the CA's certificate (DER or PEM)")
    crl = leaf(csub, "crl", "add or update a CA's revocation list (one per CA; not replaced by an older one)")
    crl.add_argument("file", help="the revocation list (DER or PEM)")
    leaf(csub, "renew", "make a new self-signed server certificate now (the old one is kept in pki/own/backup/)")
    request = leaf(csub, "request", "a certificate signing request (PKCS #10) for your CA")
    request.add_argument("--out", help="write it to this file (default: standard output)")
    request.add_argument(
        "--new-key", action="store_true", help="for a new key (kept in pki/own/pending/ until installed)"
    )
    install = leaf(csub, "install", "make a certificate your CA issued the server's")
    install.add_argument("file", help="the certificate, then the issuing CA's certificates up to the root (PEM or DER)")
    return p


def resolve_config(args: argparse.Namespace) -> Config:
    """The configuration the options name, with command-line values applied and every value checked."""
    config = load_config(getattr(args, "config", None))
    if getattr(args, "data_dir", None) is not None:
        config.server.data_dir = args.data_dir.expanduser()
    # `uacell web --host/--port` place the HMI; elsewhere they place the OPC UA server.
    listener = config.web if getattr(args, "command", None) == "web" else config.server
    if getattr(args, "host", None):
        listener.host = args.host
    if getattr(args, "port", None) is not None:
        listener.port = args.port
    if getattr(args, "web_host", None):
        config.web.host = args.web_host
    if getattr(args, "web_port", None) is not None:
        config.web.port = args.web_port
    if getattr(args, "no_web", False):
        config.web.enabled = False
    if getattr(args, "models_dir", None):
        config.server.models_dir = args.models_dir
    if getattr(args, "log_level", None):
        config.logging.level = args.log_level
    if getattr(args, "log_format", None):
        config.logging.format = args.log_format
    if getattr(args, "log_file", None) is not None:
        config.logging.file = args.log_file.expanduser()
    validate(config)
    return config


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from uacell.core import logs

    logs.configure_console(getattr(args, "log_level", "INFO"), getattr(args, "log_format", "text"))
    try:
        if args.command == "models":
            return _models(args)
        if args.command == "config":
            from uacell.cli.config_preview import run_check

            # the file named after `check`, else the global --config (or $UACELL_CONFIG), else none
            return run_check(args.file or getattr(args, "config", None), connect=args.connect)
        config = resolve_config(args)
        if args.command == "serve":
            return _serve(args, config)
        if args.command == "nodeset":
            from uacell.cli.nodeset_export import run_export

            return run_export(args, config)
        logs.configure(config)
        if args.command == "web":
            return _web(args, config)
        if args.command == "health":
            return _health(args, config)
        if args.command == "user":
            from uacell.security.users import run_user_command

            return run_user_command(args, config)
        if args.command == "cert":
            from uacell.cli.certs import run_cert_command

            return run_cert_command(args, config)
    except (ConfigError, ModelError) as exc:
        print(f"uacell: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 2


def _official_models() -> tuple[ModelFile, ...]:
    """The official models of this build's companions (``uacell.catalog``), in load order."""
    from uacell.catalog import companions

    return official_models(models_of(companions()))


def _models(args: argparse.Namespace) -> int:
    models = _official_models()
    if args.action == "fetch":
        target = fetch_models(models, force=args.force)
        print(target)
        # the models built once into a snapshot beside them, in the cache just filled (not in a
        # directory UACELL_MODELS_DIR names): first starts read it (decision 46)
        from uacell.ua.nodesets import models_snapshot_path, write_models_snapshot

        if args.force or not models_snapshot_path(models, str(target)).exists():
            print(asyncio.run(write_models_snapshot(models, str(target))))
        return 0
    locate_models(models, args.models_dir)
    print(models_dir(args.models_dir))
    return 0


def _health(args: argparse.Namespace, config: Config) -> int:
    from uacell.cli.health import check

    host = config.server.host
    host = "127.0.0.1" if host in ("0.0.0.0", "::", "[::]") else host
    endpoint = args.endpoint or f"opc.tcp://{host}:{config.server.port}/"
    ok, message = asyncio.run(check(endpoint, args.timeout))
    print(f"uacell: {endpoint}: {message}", file=sys.stdout if ok else sys.stderr)
    return 0 if ok else 1


def _serve(args: argparse.Namespace, config: Config) -> int:
    # Until the event loop takes over, a stop request ends start-up quietly (exit 0, no traceback);
    # `uacell` and `python -m uacell` install the handler first thing (uacell._entry, uacell.core.early), main() here
    # for callers that enter through it.
    early.install_early_stop()
    early.pause_gc()
    try:
        return _prepare_and_run(config)
    except BaseException:
        if early.stop_requested:
            return 0
        raise


def _prepare_and_run(config: Config) -> int:
    from uacell.core import logs

    locate_models(_official_models(), config.server.models_dir)  # fail early, with the fix, before any other work
    from uacell.cli.config_preview import check_factories

    check_factories(config)  # importable and callable, before any other work
    check_directory(config.server.data_dir, "data directory")
    if config.logging.file is not None:
        check_file(config.logging.file, "log file")
    try:
        config.server.data_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create data directory {config.server.data_dir}: {exc.strerror or exc}") from exc
    try:
        logs.configure(config)
    except OSError as exc:
        raise ConfigError(f"cannot open log file: {exc}") from exc
    return early.run(_run(config), config.server.event_loop)


async def _run(config: Config) -> int:
    from uacell.catalog import companions
    from uacell.core import notify
    from uacell.server import UacellServer

    app = UacellServer(config, companions=companions())
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    log.info("event loop: %s", "uvloop" if type(loop).__module__.startswith("uvloop") else "asyncio")
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if early.stop_requested:  # a stop whose exception some library code caught (e.g. a logging handler)
        stop.set()
    try:
        await app.setup()
    except BaseException:
        # e.g. an equipment factory failed: close what was already made (drivers connected) first.
        with contextlib.suppress(Exception):
            await app.stop()
        raise
    early.resume_gc()  # what start-up built lives as long as the server: out of the collector's way
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
    except ConfigError as exc:  # the metrics endpoint cannot listen
        print(f"uacell: {exc}", file=sys.stderr)
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
    notify.notify(f"READY=1\nSTATUS=listening on {app.endpoint}")
    await stop.wait()
    log.info("shutting down")
    notify.notify("STOPPING=1")
    try:
        # Calls under way get a moment to finish; whatever still runs after it is cancelled. The time
        # connected clients are given to leave (decision 85, after the HMI's sessions closed) is extra.
        async with asyncio.timeout(STOP_GRACE) as grace:
            if web is not None:
                await web.stop()
            announced = await app.announce_stop()
            when = grace.when()
            if when is not None:
                grace.reschedule(when + announced)
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
    from uacell.core.roles import is_loopback
    from uacell.security.pki import PkiPaths
    from uacell.web.hosting import start_web, trust_hmi

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
        server_certificate=app.served_certificate,  # not the file: a GDS's certificate counts from ApplyChanges
        https_certificate=cert,
        https_key=key,
        ua_sessions=config.web.ua_sessions,
        release_after=config.web.release_after,
        header_timeout=config.web.header_timeout,
        companions=app.companions,
    )


def _web(args: argparse.Namespace, config: Config) -> int:
    data_dir = config.server.data_dir
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create data directory {data_dir}: {exc.strerror or exc}") from exc
    return asyncio.run(_run_web(args.server, data_dir, config))


async def _run_web(server: str, data_dir: Path, config: Config) -> int:
    from uacell.catalog import companions
    from uacell.web.hosting import start_web

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    cert, key = _https_files(config)
    try:
        web = await start_web(
            server,
            data_dir,
            host=config.web.host,
            port=config.web.port,
            https_certificate=cert,
            https_key=key,
            ua_sessions=config.web.ua_sessions,
            release_after=config.web.release_after,
            header_timeout=config.web.header_timeout,
            companions=companions(),
        )
    except ConfigError as exc:
        print(f"uacell: {exc}", file=sys.stderr)
        return 2
    print(f"uacell web on {web.url}", flush=True)
    await stop.wait()
    await web.stop()
    return 0
