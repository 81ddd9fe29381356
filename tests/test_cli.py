"""The command line as an operator uses it: options anywhere, one configuration, no mistake forgiven.

Each command runs as a subprocess (``python -m uacell``) the way a shell runs it; nothing here starts a
server, so every refusal must come before anything is written.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from cryptography.hazmat.primitives.asymmetric import rsa
from helpers import free_port
from plant_ca import Authority, application_certificate, der, pem

from uacell.security.pki import PkiPaths, TrustList, make_client_certificate, thumbprint

# Cheap argon2 is not configurable from the command line; each `user add` hashes once (about 0.1 s).


def uacell(*args: str, stdin: str | None = None, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    base = {k: v for k, v in os.environ.items() if k not in ("UACELL_CONFIG", "UACELL_DATA_DIR")}
    return subprocess.run(
        [sys.executable, "-m", "uacell", *args],
        input=stdin if stdin is not None else "",
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env={**base, **(env or {})},
    )


def tree(path: Path) -> list[str]:
    return sorted(str(p.relative_to(path)) for p in path.rglob("*")) if path.exists() else []


# --- bad options: refused with one line, exit 2, nothing written ------------------------------------


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--port", "99999"], "argument --port: must be a TCP port 1..65535, not '99999'"),
        (["--port", "-1"], "argument --port: must be a TCP port 1..65535, not '-1'"),
        (["--port", "0"], "argument --port: must be a TCP port 1..65535, not '0'"),
        (["--port", "http"], "argument --port: must be a TCP port 1..65535, not 'http'"),
        (["--host", "not a host"], "argument --host: must be an IP address or host name"),
        (["--host=-bad-.example"], "argument --host: must be an IP address or host name"),
        (["--log-level", "LOUD"], "argument --log-level: invalid choice"),
        (["--log-format", "xml"], "argument --log-format: invalid choice"),
    ],
)
def test_bad_serve_options_are_refused_before_anything_is_written(tmp_path, args, expected):
    data = tmp_path / "data"
    proc = uacell("serve", "--data-dir", str(data), *args)
    assert proc.returncode == 2
    assert expected in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not data.exists()


def test_a_data_directory_that_is_a_file_is_refused(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    proc = uacell("serve", "--port", str(free_port()), "--data-dir", str(blocker))
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"uacell: data directory {blocker} is not a directory"
    assert blocker.read_text() == "x"


def test_a_log_file_that_is_a_directory_is_refused_before_the_data_directory_is_made(tmp_path):
    data = tmp_path / "data"
    proc = uacell("serve", "--port", str(free_port()), "--data-dir", str(data), "--log-file", str(tmp_path))
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"uacell: log file {tmp_path} is a directory"
    assert not data.exists()


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        ("[server]\nport = 70000", "[server] port: must be a TCP port 1..65535, not 70000"),
        ("[server]\nhost = 'a b'", "[server] host: must be an IP address or host name"),
        ("[metrics]\nport = 0", "[metrics] port: must be a TCP port 1..65535, not 0"),
        ("[logging]\nlevel = 'LOUD'", "[logging] level: must be one of"),
        ("[logging]\nformat = 'xml'", "[logging] format: must be one of text, json"),
        ("[logging]\nlevels = { asyncua = 'LOUD' }", "[logging] levels: must map logger names"),
        ("[users]\nmin_password_length = 0", "[users] min_password_length: must be 1..1024"),
        ("[logging]\nnonsense = 1", "[logging] nonsense: unknown key"),
    ],
)
def test_bad_configuration_values_are_one_line_for_every_command(tmp_path, content, expected):
    cfg = tmp_path / "uacell.toml"
    cfg.write_text(content)
    data = tmp_path / "data"
    for args in (["serve", "--port", str(free_port())], ["user", "list"], ["cert", "list"]):
        proc = uacell(*args, "--config", str(cfg), "--data-dir", str(data))
        assert proc.returncode == 2, (args, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and expected in lines[0], (args, proc.stderr)
    assert not data.exists()


# --- one configuration, options anywhere --------------------------------------------------------------


def test_global_options_are_accepted_before_and_after_the_subcommand(tmp_path):
    data = tmp_path / "data"
    for args in (
        ["--data-dir", str(data), "--log-level", "debug", "user", "list"],
        ["user", "--data-dir", str(data), "--log-level", "DEBUG", "list"],
        ["user", "list", "--log-level", "DEBUG", "--data-dir", str(data)],
    ):
        proc = uacell(*args)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.splitlines()[0] == f"{data / 'users.toml'}: no users (the file does not exist)"


def test_environment_names_the_configuration_and_the_data_directory(tmp_path):
    from_config = tmp_path / "from-config"
    from_env = tmp_path / "from-env"
    cfg = tmp_path / "uacell.toml"
    cfg.write_text(f"[server]\ndata_dir = '{from_config}'\n")
    proc = uacell(
        "user",
        "add",
        "ann",
        "--role",
        "observer",
        "--password-stdin",
        stdin="correct horse\n",
        env={"UACELL_CONFIG": str(cfg)},
    )
    assert proc.returncode == 0, proc.stderr
    assert (from_config / "users.toml").is_file()
    proc = uacell("user", "list", env={"UACELL_CONFIG": str(cfg), "UACELL_DATA_DIR": str(from_env)})
    assert proc.stdout.splitlines()[0].startswith(f"{from_env / 'users.toml'}: no users")
    # the command line wins over both
    proc = uacell("user", "list", "--data-dir", str(from_config), env={"UACELL_DATA_DIR": str(from_env)})
    assert proc.stdout.splitlines() == [f"{from_config / 'users.toml'}: 1 user", "ann\tobserver"]


# --- user -----------------------------------------------------------------------------------------------


def test_user_add_passwd_role_remove_list(tmp_path):
    d = ["--data-dir", str(tmp_path)]
    users = tmp_path / "users.toml"
    assert (
        uacell("user", "add", "alice", "--role", "operator", "--password-stdin", *d, stdin="long password\n").returncode
        == 0
    )
    before = users.read_bytes()
    again = uacell("user", "add", "alice", "--role", "admin", "--password-stdin", *d, stdin="other password\n")
    assert again.returncode == 1
    assert "user 'alice' exists" in again.stderr and "uacell user passwd" in again.stderr
    assert users.read_bytes() == before

    short = uacell("user", "passwd", "alice", "--password-stdin", *d, stdin="short\n")
    assert short.returncode == 1 and "at least 10 characters" in short.stderr
    assert users.read_bytes() == before
    assert uacell("user", "passwd", "alice", "--password-stdin", *d, stdin="a new long one\n").returncode == 0
    assert users.read_bytes() != before

    role = uacell("user", "role", "alice", "engineer", *d)
    assert role.returncode == 0 and "changed the role of user alice to engineer" in role.stdout
    listed = uacell("user", "list", *d)
    assert listed.stdout.splitlines() == [f"{users}: 1 user", "alice\tengineer"]

    for args in (["passwd", "bob", "--password-stdin"], ["role", "bob", "admin"], ["remove", "bob"]):
        proc = uacell("user", *args, *d, stdin="whatever password\n")
        assert proc.returncode == 1 and "no user 'bob'" in proc.stderr, args
    bad = uacell("user", "role", "alice", "king", *d)
    assert bad.returncode == 2 and "invalid choice: 'king'" in bad.stderr

    assert uacell("user", "remove", "alice", *d).returncode == 0
    assert uacell("user", "list", *d).stdout.splitlines() == [f"{users}: no users"]


def test_user_add_checks_the_minimum_length_from_the_configuration(tmp_path):
    cfg = tmp_path / "uacell.toml"
    cfg.write_text("[users]\nmin_password_length = 4\n")
    d = ["--data-dir", str(tmp_path / "d"), "--config", str(cfg)]
    assert uacell("user", "add", "a", "--role", "observer", "--password-stdin", *d, stdin="abc\n").returncode == 1
    assert uacell("user", "add", "a", "--role", "observer", "--password-stdin", *d, stdin="abcd\n").returncode == 0


def test_user_add_without_a_terminal_says_how(tmp_path):
    proc = uacell("user", "add", "alice", "--role", "operator", "--data-dir", str(tmp_path))
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        "uacell: no terminal to ask for the password: give it on standard input with --password-stdin"
    )
    assert not (tmp_path / "users.toml").exists()


def test_user_changes_are_in_the_audit_trail(tmp_path):
    uacell(
        "user",
        "add",
        "alice",
        "--role",
        "operator",
        "--password-stdin",
        "--data-dir",
        str(tmp_path),
        stdin="long password\n",
    )
    lines = [json.loads(line) for line in (tmp_path / "audit.log").read_text().splitlines()]
    assert [(e["event"], e["action"], e["user"], e["role"]) for e in lines] == [("user", "add", "alice", "operator")]
    assert "long password" not in (tmp_path / "audit.log").read_text()


# --- cert -----------------------------------------------------------------------------------------------


@pytest.fixture
def pki(tmp_path: Path) -> tuple[Path, PkiPaths, bytes]:
    """A data directory with one rejected client certificate."""
    paths = PkiPaths.in_data_dir(tmp_path)
    der, _ = make_client_certificate("urn:test:mes", common_name="MES line 3")
    TrustList(paths).reject(der)
    return tmp_path, paths, der


def test_rejected_certificates_are_named_by_thumbprint(pki):
    _, paths, der = pki
    assert [p.name for p in paths.rejected.iterdir()] == [f"{thumbprint(der)}.der"]


def test_cert_list_shows_subject_uri_thumbprint_and_validity(pki):
    data, paths, der = pki
    proc = uacell("cert", "list", "--data-dir", str(data))
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0] == f"{paths.root}: 1 certificate"
    assert lines[1].startswith(f"rejected {thumbprint(der)}  MES line 3  urn:test:mes  valid ")
    assert lines[1].endswith(str(paths.rejected / f"{thumbprint(der)}.der"))


def test_cert_commands_name_a_certificate_the_security_policies_refuse(tmp_path):
    """Decision 101: a client certificate with a 1024-bit key (made here from RFC 5280) is trusted as asked,
    with a warning that the server refuses it anyway; ``cert list`` says so on its line; ``cert remove``
    takes the certificate's file."""
    data = tmp_path / "data"
    small_key = rsa.generate_private_key(public_exponent=65537, key_size=1024)
    cert_file = tmp_path / "old-hmi.der"
    cert_file.write_bytes(der(application_certificate("urn:plant:old-hmi", "Old HMI", small_key)))
    d = ["--data-dir", str(data)]
    trusted = uacell("cert", "trust", str(cert_file), *d)
    assert trusted.returncode == 0, trusted.stderr
    assert "refuses this certificate" in trusted.stderr and "1024 bits" in trusted.stderr
    listed = uacell("cert", "list", *d).stdout.splitlines()
    assert len(listed) == 2 and "Old HMI" in listed[1] and "REFUSED BY THE SECURITY POLICIES" in listed[1]
    removed = uacell("cert", "remove", str(cert_file), *d)
    assert removed.returncode == 0 and "removed" in removed.stdout, removed.stderr
    assert list(PkiPaths.in_data_dir(data).trusted.iterdir()) == []


def test_cert_trust_reject_remove_by_thumbprint_prefix(pki):
    data, paths, der = pki
    tp = thumbprint(der)
    d = ["--data-dir", str(data)]
    assert uacell("cert", "trust", tp[:8], *d).returncode == 0
    assert [p.read_bytes() for p in paths.trusted.iterdir()] == [der]
    assert list(paths.rejected.iterdir()) == []
    assert TrustList(paths).is_trusted(der)  # what a running server checks at every secure connection

    assert uacell("cert", "reject", tp.upper()[:10], *d).returncode == 0
    assert list(paths.trusted.iterdir()) == []
    assert [p.name for p in paths.rejected.iterdir()] == [f"{tp}.der"]
    assert not TrustList(paths).is_trusted(der)

    assert uacell("cert", "remove", tp, *d).returncode == 0
    assert list(paths.rejected.iterdir()) == []
    lines = [json.loads(line) for line in (data / "audit.log").read_text().splitlines()]
    assert [e["action"] for e in lines] == ["trust", "reject", "remove"]


def test_cert_trust_a_file(tmp_path):
    der, _ = make_client_certificate("urn:test:hmi", common_name="HMI")
    f = tmp_path / "hmi cert.der"
    f.write_bytes(der)
    proc = uacell("cert", "trust", str(f), "--data-dir", str(tmp_path / "d"))
    assert proc.returncode == 0, proc.stderr
    assert TrustList(PkiPaths.in_data_dir(tmp_path / "d")).is_trusted(der)


def test_cert_commands_refuse_unknown_short_or_ambiguous_ids_and_change_nothing(pki):
    data, paths, der = pki
    other, _ = make_client_certificate("urn:test:other")
    TrustList(paths).reject(other)
    before = tree(paths.root)
    d = ["--data-dir", str(data)]
    cases = [
        (["trust", "0000000000"], "no rejected or trusted certificate has a thumbprint starting with 0000000000"),
        (["trust", "ab"], "is neither a certificate file nor a thumbprint"),
        (["trust", "not-hex-at-all"], "is neither a certificate file nor a thumbprint"),
        (["reject", thumbprint(der)], "no trusted certificate has a thumbprint"),
        (["remove", "ffffffffff"], "no trusted or issuer or rejected certificate"),
    ]
    for args, expected in cases:
        proc = uacell("cert", *args, *d)
        assert proc.returncode == 1, (args, proc.stdout)
        assert expected in proc.stderr, (args, proc.stderr)
    assert tree(paths.root) == before


def test_cert_issuer_and_crl_add_a_plant_ca_and_its_revocation_lists(tmp_path):
    """`uacell cert issuer` and `uacell cert crl` (decision 92), with a CA made from RFC 5280's rules."""
    root = Authority.root()
    issuing = root.intermediate()
    mes, _ = issuing.application("urn:plant:mes")
    files = {
        "root.der": root.der,
        "issuing.pem": pem(issuing.cert),
        "mes.der": der(mes),
        "issuing.crl": issuing.crl(issued=dt.datetime.now(dt.UTC) - dt.timedelta(hours=2)),
        "root.crl": root.crl(),
        "junk.crl": b"junk",
    }
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    d = ["--data-dir", str(tmp_path / "d")]
    paths = PkiPaths.in_data_dir(tmp_path / "d")

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return uacell("cert", *args, *d)

    refused = run("issuer", str(tmp_path / "mes.der"))  # an application's certificate is no CA
    assert refused.returncode == 1 and "is not a CA's certificate" in refused.stderr
    refused = run("crl", str(tmp_path / "issuing.crl"))  # nobody known signed it yet
    assert refused.returncode == 1 and "no CA in" in refused.stderr and "Plant Issuing CA" in refused.stderr
    refused = run("crl", str(tmp_path / "junk.crl"))
    assert refused.returncode == 1 and "is not a revocation list" in refused.stderr
    assert run("trust", str(tmp_path / "root.der")).returncode == 0
    added = run("issuer", str(tmp_path / "issuing.pem"))
    assert added.returncode == 0, added.stderr
    assert [p.read_bytes() for p in paths.issuers.iterdir()] == [issuing.der]
    assert run("crl", str(tmp_path / "root.crl")).returncode == 0
    assert run("crl", str(tmp_path / "issuing.crl")).returncode == 0
    assert TrustList(paths).admit([mes], "urn:plant:mes")  # the chain the files describe
    # a newer list replaces the CA's; an older one does not
    issuing.revoke(mes)
    newer = issuing.crl()
    (tmp_path / "newer.crl").write_bytes(newer)
    assert run("crl", str(tmp_path / "newer.crl")).returncode == 0
    assert len(list(paths.crl.iterdir())) == 2
    assert not TrustList(paths).admit([mes], "urn:plant:mes")  # revoked now
    older = run("crl", str(tmp_path / "issuing.crl"))
    assert older.returncode == 1 and "is older than the list kept" in older.stderr
    listed = run("list").stdout.splitlines()
    assert any(line.startswith("issuer ") and "Plant Issuing CA" in line for line in listed)
    crl_lines = [line for line in listed if line.startswith("crl ")]
    assert len(crl_lines) == 2 and any("Plant Issuing CA  1 revoked  current" in line for line in crl_lines)
    # a list past its nextUpdate (decision 98) says so
    old_ca = Authority.root("Old CA", key_index=6)
    (paths.crl / "old.crl").write_bytes(old_ca.crl(issued=dt.datetime.now(dt.UTC) - dt.timedelta(days=30)))
    assert any("Old CA  0 revoked  stale" in line for line in run("list").stdout.splitlines())
    (paths.crl / "old.crl").unlink()
    trail = [json.loads(line)["action"] for line in (tmp_path / "d" / "audit.log").read_text().splitlines()]
    assert trail == ["trust", "issuer", "crl", "crl", "crl"]


def test_cert_renew_keeps_the_old_pair(tmp_path):
    from uacell.security.pki import ensure_server_certificate

    paths = PkiPaths.in_data_dir(tmp_path)
    ensure_server_certificate(paths, "urn:uacell:server", ["127.0.0.1"])
    old = paths.cert.read_bytes()
    proc = uacell("cert", "renew", "--data-dir", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    assert paths.cert.read_bytes() != old
    backups = sorted(p.name for p in paths.backup.iterdir())
    assert len(backups) == 2 and backups[0].startswith("cert-") and backups[1].startswith("key-")
    assert [p.read_bytes() for p in paths.backup.glob("cert-*")] == [old]
    assert thumbprint(paths.cert.read_bytes()) in proc.stdout


def test_a_thumbprint_prefix_naming_two_certificates_is_refused(tmp_path, monkeypatch):
    from uacell.cli import certs
    from uacell.security.pki import generate_key

    paths = PkiPaths.in_data_dir(tmp_path)
    key = generate_key()
    seen: dict[str, bytes] = {}
    while True:  # 17 certificates at most share a first hex digit
        der, _ = make_client_certificate("urn:test:x", key=key)
        if thumbprint(der)[0] in seen:
            break
        seen[thumbprint(der)[0]] = der
    TrustList(paths).reject(der)
    TrustList(paths).reject(seen[thumbprint(der)[0]])
    monkeypatch.setattr(certs, "MIN_PREFIX", 1)
    with pytest.raises(certs.CertError, match="names more than one certificate"):
        certs.trust(paths, thumbprint(der)[0])
    assert list(paths.trusted.iterdir()) == []
    assert certs.trust(paths, thumbprint(der)).name == f"{thumbprint(der)}.der"


def test_config_check_takes_the_global_config_option_too() -> None:
    from uacell.core.cell_file import builtin_cell_path

    path = str(builtin_cell_path("modbus-robot"))
    for args in (("config", "check", path), ("--config", path, "config", "check")):
        proc = uacell(*args)
        assert proc.returncode == 0, proc.stderr
        assert f"configuration: {path}" in proc.stdout
        assert "Controllers/Cabinet  ControllerType  equipment: uacell.gateway.robot:modbus_signals" in proc.stdout


def test_models_fetch_writes_the_models_snapshot_beside_the_files(tmp_path: Path) -> None:
    """With the NodeSet files already in the cache, `uacell models fetch` fetches nothing and builds
    the models' snapshot beside them (decision 46), once; not into a directory UACELL_MODELS_DIR names."""
    from helpers import official

    from uacell.models.source import NPM_PACKAGE, NPM_VERSION, locate_models
    from uacell.ua.snapshot import PREFIX, SUFFIX

    cache = tmp_path / "xdg" / "uacell" / "nodesets" / f"{NPM_PACKAGE}-{NPM_VERSION}"
    cache.mkdir(parents=True)
    for path in locate_models(official()).values():
        (cache / path.name).symlink_to(path.resolve())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    src = str(Path(__file__).resolve().parents[1] / "src")
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "xdg"), "UACELL_MODELS_DIR": str(elsewhere)}
    env["PYTHONPATH"] = src
    cmd = [sys.executable, "-m", "uacell", "models", "fetch"]
    first = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120, check=False)
    assert first.returncode == 0, first.stderr
    [snapshot] = cache.glob(f"{PREFIX}*{SUFFIX}")
    assert first.stdout.split() == [str(cache), str(snapshot)]
    assert list(elsewhere.iterdir()) == []
    again = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120, check=False)
    assert again.returncode == 0 and again.stdout.split() == [str(cache)]  # there already: not rebuilt


def test_cert_request_and_install_a_certificate_the_plant_ca_issued(tmp_path):
    """`uacell cert request` and `uacell cert install` (decision 95) before the first start: a new key,
    the request signed by a CA made from RFC 5280's rules, what it issued installed with its chain."""
    d = ["--data-dir", str(tmp_path / "d")]
    paths = PkiPaths.in_data_dir(tmp_path / "d")
    root = Authority.root()
    issuing = root.intermediate()

    refused = uacell("cert", "request", *d)  # no key yet: say how to get one
    assert refused.returncode == 1 and "ask for a new key" in refused.stderr
    made = uacell("cert", "request", "--new-key", "--out", str(tmp_path / "uacell.csr"), *d)
    assert made.returncode == 0, made.stderr
    assert paths.pending_key.exists() and not paths.key.exists()
    issued = issuing.sign_request((tmp_path / "uacell.csr").read_bytes())
    # a file with the CA's certificates in the wrong order is refused and changes nothing
    (tmp_path / "wrong.pem").write_bytes(pem(issued) + pem(root.cert) + pem(issuing.cert))
    wrong = uacell("cert", "install", str(tmp_path / "wrong.pem"), *d)
    assert wrong.returncode == 1 and "did not issue certificate 1" in wrong.stderr
    assert not paths.cert.exists() and paths.pending_key.exists()
    (tmp_path / "issued.pem").write_bytes(pem(issued) + pem(issuing.cert))
    installed = uacell("cert", "install", str(tmp_path / "issued.pem"), *d)
    assert installed.returncode == 0, installed.stderr
    assert f"server certificate {thumbprint(der(issued))} from" in installed.stdout
    assert "with 1 CA certificate(s) and its new key" in installed.stdout
    assert paths.cert.read_bytes() == der(issued) and not paths.pending_key.exists()
    listed = uacell("cert", "list", *d).stdout.splitlines()
    assert any(line.startswith(f"own      {thumbprint(der(issued))}") for line in listed)
    assert any(line.startswith(f"own-ca   {thumbprint(issuing.der)}  Plant Issuing CA") for line in listed)
    trail = [json.loads(line) for line in (tmp_path / "d" / "audit.log").read_text().splitlines()]
    assert [e["action"] for e in trail if e.get("event") == "cert"] == ["request", "install"]
