"""The server's certificate sent with the certificates of the CA that issued it (decision 95).

OPC 10000-6 6.2.6: where an application sends its certificate (the SenderCertificate of
OpenSecureChannel, an endpoint's ServerCertificate, CreateSession's serverCertificate) and the
certificate is part of a chain, the chain follows it, each issuer's DER appended. asyncua sends the
server's certificate alone in the endpoints and at CreateSession, so the endpoints get the chain
appended once they are made, and each channel's policy holds the chain as its certificate.

ActivateSession's clientSignature (OPC 10000-4 5.7.3.2) covers the serverCertificate followed by the
serverNonce, "only the leaf Certificate" when the serverCertificate is a chain, and "for backward
compatibility a Server shall check the signature with the full chain if the check with the leaf
Certificate fails" (node-opcua signs the whole chain; asyncua's client the leaf). asyncua checks it
against the policy's certificate, so the policy's check tries the leaf first, then the chain.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from asyncua.server.server import Server
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization

from uacell.ua.door import configure, swap


def send_with_chain(server: Server, issuers: bytes) -> None:
    """The server's certificate goes with ``issuers`` (DER, appended in order) from the next start."""
    if not issuers:
        return
    setup = server._setup_server_nodes

    async def setup_with_chain() -> None:
        await setup()
        _send(server, issuers)

    swap(server, "Server._setup_server_nodes", setup_with_chain)


def served_certificate(server: Server) -> bytes:
    """The DER of the certificate new secure channels are opened with (the last ``use_certificate``'s, or
    the one loaded at start), without the CA's that may follow it."""
    return bytes(server.iserver.certificate.public_bytes(serialization.Encoding.DER))


def use_certificate(server: Server, certificate: x509.Certificate, key: Any, issuers: bytes) -> None:
    """Secure channels opened from now on use ``certificate`` (followed by ``issuers``) and ``key``; those
    open keep what they were opened with (OPC 10000-12 ApplyChanges, decision 96)."""
    configure(server.iserver, "InternalServer.certificate", certificate)
    configure(server.iserver, "InternalServer.private_key", key)
    for factory in server._policies:
        configure(factory, "SecurityPolicyFactory.certificate", certificate)
        configure(factory, "SecurityPolicyFactory.private_key", key)
    leaf = certificate.public_bytes(serialization.Encoding.DER)
    for endpoint in server.iserver.endpoints:
        if endpoint.ServerCertificate:
            endpoint.ServerCertificate = leaf
    _send(server, issuers)


def _send(server: Server, issuers: bytes) -> None:
    """The endpoints and the channels' policies with the server's certificate followed by ``issuers``."""
    for endpoint in server.iserver.endpoints:
        if endpoint.ServerCertificate:
            endpoint.ServerCertificate += issuers
    for factory in server._policies:
        create = type(factory).create.__get__(factory)  # asyncua's, bound to this factory
        swap(factory, "SecurityPolicyFactory.create", _chained(create, issuers) if issuers else create)


def _chained(create: Callable[[Any], Any], issuers: bytes) -> Callable[[Any], Any]:
    def create_chained(peer_certificate: Any) -> Any:
        policy = create(peer_certificate)
        leaf: bytes | None = policy.host_certificate
        if leaf:
            full = leaf + issuers
            policy.host_certificate = full
            crypto = policy.asymmetric_cryptography
            swap(crypto, "Cryptography.verify", _leaf_first(crypto.verify, leaf, full))
        return policy

    return create_chained


def _leaf_first(verify: Callable[[bytes, bytes], None], leaf: bytes, full: bytes) -> Callable[[bytes, bytes], None]:
    def verify_leaf_first(data: bytes, signature: bytes) -> None:
        if data.startswith(full):
            try:
                verify(leaf + data[len(full) :], signature)
                return
            except InvalidSignature:
                pass  # signed over the whole chain, as before OPC 10000-4 1.04's errata
        verify(data, signature)

    return verify_leaf_first
