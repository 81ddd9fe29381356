"""X.509 user certificates, pure: the user store's bindings and the checks of OPC 10000-4 (5.6.3, 7.41.5)
on an X509IdentityToken and its userTokenSignature (decision 84). Over TCP: test_certificate_login_server.py."""

from __future__ import annotations

import datetime as dt
import os
import tomllib
from pathlib import Path

import pytest
from argon2 import PasswordHasher
from asyncua import ua
from cryptography.hazmat.primitives.asymmetric import rsa
from user_certificates import AES256_RSAPSS, BASIC256SHA256, RSA_PSS_SHA256, RSA_SHA256, user_certificate

from uacell.core.roles import Role
from uacell.security.certificate_login import (
    BAD_IDENTITY_TOKEN_INVALID,
    BAD_IDENTITY_TOKEN_REJECTED,
    BAD_USER_SIGNATURE_INVALID,
    CertificateLogin,
    TokenRefused,
    check_user_certificate,
)
from uacell.security.chain import first_certificate
from uacell.security.users import User, UserError, UserStore, load_user_certificate, thumbprint

FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)
SERVER_CERT = b"\x30\x03server certificate DER"  # what the challenge starts with; its content plays no part here
NONCE = os.urandom(32)


def now() -> dt.datetime:
    """The time of the check, taken when it runs: a module-level "now" is from collection, which a slow
    run puts minutes before certificates a test makes."""
    return dt.datetime.now(dt.UTC)


ALICE = user_certificate("alice")
BOB = user_certificate("bob")


@pytest.fixture
def store(tmp_path: Path) -> UserStore:
    store = UserStore.in_data_dir(tmp_path, hasher=FAST)
    store.add("alice", "operator", None, certificate=ALICE.der)
    return store


def check(
    store: UserStore, der: bytes | None, algorithm: str | None, signature: bytes | None, **kw: object
) -> CertificateLogin:
    args: dict[str, object] = {"policy_uri": BASIC256SHA256, "challenge": SERVER_CERT + NONCE, "now": now()}
    args.update(kw)
    return check_user_certificate(der, algorithm, signature, users=store, **args)  # type: ignore[arg-type]


def refused(store: UserStore, *args: object, **kw: object) -> int:
    with pytest.raises(TokenRefused) as info:
        check(store, *args, **kw)  # type: ignore[arg-type]
    return info.value.code


# the user store -----------------------------------------------------------------------------------------


def test_a_certificate_binds_a_user_and_is_kept_as_its_thumbprint(store: UserStore) -> None:
    assert store.user_of_certificate(ALICE.der) == ("alice", Role.OPERATOR)
    assert store.user_of_certificate(BOB.der) is None
    entry = tomllib.loads(store.path.read_text())["users"]["alice"]
    assert entry == {"role": "operator", "certificates": [thumbprint(ALICE.der)]}  # no hash: no password
    assert len(thumbprint(ALICE.der)) == 64
    assert store.list() == [User("alice", Role.OPERATOR, password=False, certificates=(thumbprint(ALICE.der),))]


def test_a_certificate_only_user_has_no_password_to_guess(store: UserStore) -> None:
    assert store.verify("alice", "") is None
    assert store.verify("alice", "anything at all") is None
    store.set_password("alice", "a password now")
    assert store.verify("alice", "a password now") is Role.OPERATOR
    assert store.user_of_certificate(ALICE.der) == ("alice", Role.OPERATOR)  # both ways


def test_one_certificate_belongs_to_one_user(store: UserStore) -> None:
    store.add("bob", "engineer", "bobs password")
    before = store.path.read_bytes()
    with pytest.raises(UserError, match="bound to user 'alice' already"):
        store.add_certificate("bob", ALICE.der)
    with pytest.raises(UserError, match="bound to this user already"):
        store.add_certificate("alice", ALICE.der)
    with pytest.raises(UserError, match="bound to user 'alice' already"):
        store.add("carol", "admin", None, certificate=ALICE.der)
    assert store.path.read_bytes() == before
    assert store.add_certificate("bob", BOB.der) == thumbprint(BOB.der)
    assert store.user_of_certificate(BOB.der) == ("bob", Role.ENGINEER)
    store.set_role("bob", "admin")  # a role change keeps the certificates
    assert store.user_of_certificate(BOB.der) == ("bob", Role.ADMIN)


def test_removing_a_certificate_never_leaves_a_user_without_a_login(store: UserStore) -> None:
    before = store.path.read_bytes()
    with pytest.raises(UserError, match="only way user 'alice' logs in"):
        store.remove_certificate("alice", thumbprint(ALICE.der))
    with pytest.raises(UserError, match="has no certificate"):
        store.remove_certificate("alice", thumbprint(BOB.der))
    assert store.path.read_bytes() == before
    store.set_password("alice", "now a password")
    store.remove_certificate("alice", thumbprint(ALICE.der))
    assert store.user_of_certificate(ALICE.der) is None
    assert store.list() == [User("alice", Role.OPERATOR)]
    with pytest.raises(UserError, match="needs a password or a certificate"):
        store.add("dave", "operator", None)


def test_a_certificate_in_two_users_logs_in_as_nobody(store: UserStore, caplog: pytest.LogCaptureFixture) -> None:
    # an edit by hand: the CLI refuses to make this
    text = store.path.read_text() + f'\n[users.eve]\nrole = "admin"\ncertificates = ["{thumbprint(ALICE.der)}"]\n'
    store.path.write_text(text)
    os.utime(store.path, ns=(1, 1))
    assert store.user_of_certificate(ALICE.der) is None
    assert "bound to ['alice', 'eve']: nobody logs in with it" in caplog.text


@pytest.mark.parametrize(
    "entry",
    [
        'role = "operator"\ncertificates = ["not-a-thumbprint"]',
        'role = "operator"\ncertificates = "' + "a" * 64 + '"',
        'role = "operator"',  # no way to log in
    ],
)
def test_unusable_entries_are_skipped(tmp_path: Path, entry: str) -> None:
    store = UserStore.in_data_dir(tmp_path, hasher=FAST)
    store.path.write_text(f"[users.mallory]\n{entry}\n")
    assert store.list() == []


def test_certificate_files_pem_der_and_refusals(tmp_path: Path) -> None:
    pem, _ = ALICE.write(tmp_path, "alice")
    der = tmp_path / "alice.der"
    der.write_bytes(ALICE.der)
    assert load_user_certificate(pem) == ALICE.der == load_user_certificate(der)
    junk = tmp_path / "junk.pem"
    junk.write_text("-----BEGIN CERTIFICATE-----\nnot base64\n-----END CERTIFICATE-----\n")
    with pytest.raises(UserError, match=r"holds no X\.509 certificate"):
        load_user_certificate(junk)
    with pytest.raises(UserError, match="cannot read"):
        load_user_certificate(tmp_path / "missing.pem")
    small = tmp_path / "small.der"  # a key the security policies refuse (decision 102): bound, it never logs in
    small.write_bytes(user_certificate("s", key=rsa.generate_private_key(public_exponent=65537, key_size=1024)).der)
    with pytest.raises(UserError, match="1024 bits"):
        load_user_certificate(small)


# the token's checks -------------------------------------------------------------------------------------


def test_a_bound_certificate_signed_for_this_nonce_logs_in(store: UserStore) -> None:
    login = check(store, ALICE.der, RSA_SHA256, ALICE.sign(SERVER_CERT + NONCE))
    assert (login.user, login.role, login.thumbprint) == ("alice", Role.OPERATOR, thumbprint(ALICE.der))
    pss = check(
        store,
        ALICE.der,
        RSA_PSS_SHA256,
        ALICE.sign(SERVER_CERT + NONCE, RSA_PSS_SHA256),
        policy_uri=AES256_RSAPSS,
    )
    assert pss.user == "alice"


def test_the_signature_proves_the_key_for_this_session_and_nonce(store: UserStore) -> None:
    good = ALICE.sign(SERVER_CERT + NONCE)
    assert refused(store, ALICE.der, RSA_SHA256, BOB.sign(SERVER_CERT + NONCE)) == BAD_USER_SIGNATURE_INVALID
    assert refused(store, ALICE.der, RSA_SHA256, ALICE.sign(SERVER_CERT + os.urandom(32))) == BAD_USER_SIGNATURE_INVALID
    assert refused(store, ALICE.der, RSA_SHA256, ALICE.sign(NONCE)) == BAD_USER_SIGNATURE_INVALID  # no server cert
    assert refused(store, ALICE.der, RSA_SHA256, None) == BAD_USER_SIGNATURE_INVALID
    assert refused(store, ALICE.der, None, good) == BAD_USER_SIGNATURE_INVALID
    # the algorithm is the policy's: PSS under Basic256Sha256 is refused, even with a signature that verifies
    pss = ALICE.sign(SERVER_CERT + NONCE, RSA_PSS_SHA256)
    assert refused(store, ALICE.der, RSA_PSS_SHA256, pss) == BAD_USER_SIGNATURE_INVALID
    assert refused(store, ALICE.der, RSA_SHA256, good, policy_uri=AES256_RSAPSS) == BAD_USER_SIGNATURE_INVALID
    assert refused(store, ALICE.der, RSA_SHA256, good, policy_uri="") == BAD_USER_SIGNATURE_INVALID


def test_an_unreadable_certificate_is_an_invalid_token(store: UserStore) -> None:
    assert refused(store, b"", RSA_SHA256, b"x") == BAD_IDENTITY_TOKEN_INVALID
    assert refused(store, None, RSA_SHA256, b"x") == BAD_IDENTITY_TOKEN_INVALID
    assert refused(store, ALICE.der[:-10], RSA_SHA256, b"x") == BAD_IDENTITY_TOKEN_INVALID


def test_a_certificate_out_of_its_validity_or_not_for_signing_is_rejected(tmp_path: Path) -> None:
    store = UserStore.in_data_dir(tmp_path, hasher=FAST)
    expired = user_certificate("old", not_before=now() - dt.timedelta(days=400), days=365)
    future = user_certificate("later", not_before=now() + dt.timedelta(days=1))
    encipher = user_certificate("encipher only", digital_signature=False)
    unrestricted = user_certificate("any use", key_usage=False)
    for i, cert in enumerate((expired, future, encipher, unrestricted)):
        store.add(f"u{i}", "operator", None, certificate=cert.der)
    steps = [
        (expired, ua.StatusCodes.BadCertificateTimeInvalid),
        (future, ua.StatusCodes.BadCertificateTimeInvalid),
        (encipher, ua.StatusCodes.BadCertificateUseNotAllowed),
    ]
    for cert, step in steps:
        with pytest.raises(TokenRefused) as info:
            check(store, cert.der, RSA_SHA256, cert.sign(SERVER_CERT + NONCE))
        assert (info.value.code, info.value.certificate_code) == (BAD_IDENTITY_TOKEN_REJECTED, step)
    assert check(store, unrestricted.der, RSA_SHA256, unrestricted.sign(SERVER_CERT + NONCE)).user == "u3"


def test_a_key_the_token_policy_does_not_allow_is_rejected_after_its_signature(tmp_path: Path) -> None:
    """OPC 10000-7: the policies uacell offers sign with RSA keys of 2048 to 4096 bits (decision 101). A
    bound user certificate with a 1024-bit key proves its key, and is then rejected; the reason is for the
    server's log only."""
    store = UserStore.in_data_dir(tmp_path, hasher=FAST)
    small = user_certificate("old badge", key=rsa.generate_private_key(public_exponent=65537, key_size=1024))
    store.add("olga", "operator", None, certificate=small.der)
    with pytest.raises(TokenRefused) as info:
        check(store, small.der, RSA_SHA256, small.sign(SERVER_CERT + NONCE))
    assert info.value.code == BAD_IDENTITY_TOKEN_REJECTED and "1024" in info.value.why
    assert info.value.certificate_code == ua.StatusCodes.BadCertificatePolicyCheckFailed  # for its audit event
    # without the key, the signature fails first, as for any certificate
    assert refused(store, small.der, RSA_SHA256, ALICE.sign(SERVER_CERT + NONCE)) == BAD_USER_SIGNATURE_INVALID


def test_a_certificate_bound_to_nobody_is_rejected_after_its_signature(store: UserStore) -> None:
    with pytest.raises(TokenRefused) as info:
        check(store, BOB.der, RSA_SHA256, BOB.sign(SERVER_CERT + NONCE))
    assert (info.value.code, info.value.certificate_code) == (
        BAD_IDENTITY_TOKEN_REJECTED,
        ua.StatusCodes.BadCertificateUntrusted,  # the binding is the user certificates' trust list
    )
    assert refused(store, BOB.der, RSA_SHA256, BOB.sign(SERVER_CERT + NONCE)) == BAD_IDENTITY_TOKEN_REJECTED
    # without the key, a client learns nothing about the user store: the signature fails first
    assert refused(store, BOB.der, RSA_SHA256, ALICE.sign(SERVER_CERT + NONCE)) == BAD_USER_SIGNATURE_INVALID


def test_a_chain_after_the_certificate_is_read_as_the_certificate(store: UserStore) -> None:
    chain = ALICE.der + BOB.der  # the user's certificate, then an issuer's
    assert first_certificate(chain) == ALICE.der
    assert first_certificate(b"\x30") == b"\x30"
    assert first_certificate(b"\x30\x84\xff\xff\xff\xff") == b"\x30\x84\xff\xff\xff\xff"  # longer than the data
    assert check(store, chain, RSA_SHA256, ALICE.sign(SERVER_CERT + NONCE)).user == "alice"


def test_the_signature_table_is_the_one_of_each_offered_policy() -> None:
    """``SIGNATURE_ALGORITHM`` is written from OPC 10000-7; each security policy uacell offers signs by it."""
    from asyncua.crypto.security_policies import SECURITY_POLICY_TYPE_MAP

    from uacell.security.certificate_login import SIGNATURE_ALGORITHM
    from uacell.security.policy import SECURE_POLICIES

    for offered in SECURE_POLICIES:
        policy = SECURITY_POLICY_TYPE_MAP[offered][0]
        assert SIGNATURE_ALGORITHM[policy.URI] == policy.AsymmetricSignatureURI


def test_a_signature_over_the_servers_whole_chain_counts_when_the_server_sends_one(store: UserStore) -> None:
    """OPC 10000-4 5.7.3.2: the token is signed over the server certificate alone; a server that sends its
    CA's certificates after it (decision 95) also accepts a signature over the whole chain."""
    chain = SERVER_CERT + b"\x30\x05CA DER"
    over_chain = ALICE.sign(chain + NONCE, RSA_SHA256)
    over_leaf = ALICE.sign(SERVER_CERT + NONCE, RSA_SHA256)
    assert check(store, ALICE.der, RSA_SHA256, over_leaf, chain_challenge=chain + NONCE).user == "alice"
    assert check(store, ALICE.der, RSA_SHA256, over_chain, chain_challenge=chain + NONCE).user == "alice"
    assert refused(store, ALICE.der, RSA_SHA256, over_chain) == BAD_USER_SIGNATURE_INVALID
    other = ALICE.sign(SERVER_CERT + b"another nonce", RSA_SHA256)
    assert refused(store, ALICE.der, RSA_SHA256, other, chain_challenge=chain + NONCE) == (BAD_USER_SIGNATURE_INVALID)
