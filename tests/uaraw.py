"""A hand-built OPC UA client for security tests: every message is made here from asyncua's ua classes
and binary encoders and sent over a raw TCP connection, so the tests can send what a polite client
would refuse to (a policy the server does not offer, a replayed or mis-encrypted user token).

Only asyncua's SecureConnection is reused, for chunk framing, signing and encryption of whatever
policy the test chooses.
"""

from __future__ import annotations

import asyncio
import os
import struct
from dataclasses import dataclass
from typing import Any

from asyncua import ua
from asyncua.common.connection import SecureConnection, TransportLimits
from asyncua.common.utils import Buffer
from asyncua.crypto import uacrypto
from asyncua.crypto.security_policies import SecurityPolicy, SecurityPolicyNone
from asyncua.ua.ua_binary import header_from_binary, nodeid_from_binary, struct_from_binary, struct_to_binary

TIMEOUT = 30.0
_FAULT = ua.NodeId(ua.ObjectIds.ServiceFault_Encoding_DefaultBinary)


class Refused(Exception):
    """The server answered with an OPC UA TCP Error message (and closes the connection)."""

    def __init__(self, message: ua.ErrorMessage) -> None:
        super().__init__(f"{ua.StatusCode(message.Error.value).name}: {message.Reason}")
        self.code = message.Error.value


class Fault(Exception):
    """The server answered a request with a ServiceFault."""

    def __init__(self, code: int) -> None:
        super().__init__(ua.StatusCode(code).name)
        self.code = code


@dataclass
class Session:
    response: ua.CreateSessionResult
    token: ua.NodeId

    @property
    def nonce(self) -> bytes:
        return self.response.ServerNonce

    @property
    def server_certificate(self) -> bytes:
        return self.response.ServerCertificate


class RawClient:
    """One TCP connection carrying hand-built messages (Hello, OpenSecureChannel, session services)."""

    def __init__(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, url: str, policy: SecurityPolicy | None = None
    ) -> None:
        self.reader = reader
        self.writer = writer
        self.url = url
        self.policy = policy or SecurityPolicyNone()
        self.connection = SecureConnection(self.policy, TransportLimits())
        self.request_id = 0
        self.handle = 0
        self.auth = ua.NodeId()

    @classmethod
    async def connect(
        cls, host: str, port: int, *, policy: SecurityPolicy | None = None, sock: Any = None, url: str | None = None
    ) -> RawClient:
        if sock is not None:
            reader, writer = await asyncio.wait_for(asyncio.open_connection(sock=sock), TIMEOUT)
        else:
            reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), TIMEOUT)
        return cls(reader, writer, url or f"opc.tcp://{host}:{port}/", policy)

    async def close(self) -> None:
        self.writer.close()
        try:
            await self.writer.wait_closed()
        except (ConnectionError, OSError):
            pass

    async def __aenter__(self) -> RawClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # framing ---------------------------------------------------------------------------------------

    async def _read(self) -> tuple[ua.Header, Buffer]:
        head = await asyncio.wait_for(self.reader.readexactly(8), TIMEOUT)
        _, _, size = struct.unpack("<3scI", head)
        rest = await asyncio.wait_for(self.reader.readexactly(size - 8), TIMEOUT)
        buf = Buffer(head + rest)
        return header_from_binary(buf), buf

    async def _exchange(self, data: bytes) -> Any:
        self.writer.write(data)
        await self.writer.drain()
        header, body = await self._read()
        if header.MessageType == ua.MessageType.Error:
            raise Refused(struct_from_binary(ua.ErrorMessage, body))
        return self.connection.receive_from_header_and_body(header, body)

    async def at_eof(self) -> bool:
        """True when the server has closed the connection (waits for it)."""
        data = await asyncio.wait_for(self.reader.read(1), TIMEOUT)
        return data == b""

    # messages --------------------------------------------------------------------------------------

    async def hello(self) -> ua.Acknowledge:
        hello = ua.Hello()
        hello.EndpointUrl = self.url
        hello.ReceiveBufferSize = hello.SendBufferSize = 65535
        self.writer.write(ua.ua_binary.uatcp_to_binary(ua.MessageType.Hello, hello))
        await self.writer.drain()
        header, body = await self._read()
        if header.MessageType == ua.MessageType.Error:
            raise Refused(struct_from_binary(ua.ErrorMessage, body))
        return struct_from_binary(ua.Acknowledge, body)

    async def open_channel(self, mode: ua.MessageSecurityMode | None = None) -> ua.OpenSecureChannelResult:
        params = _open_parameters(self.policy, mode)
        self.request_id += 1
        msg = await self._exchange(_open_message(self.connection, params, self.request_id))
        response = struct_from_binary(ua.OpenSecureChannelResponse, msg.body())
        self.connection.set_channel(response.Parameters, params.RequestType, params.ClientNonce)
        return response.Parameters

    async def request(self, request: Any, response_type: type) -> Any:
        """Send one service request; return its response, or raise Fault for a ServiceFault."""
        self.handle += 1
        self.request_id += 1
        request.RequestHeader.AuthenticationToken = self.auth
        request.RequestHeader.RequestHandle = self.handle
        request.RequestHeader.TimeoutHint = int(TIMEOUT * 1000)
        data = self.connection.message_to_binary(struct_to_binary(request), request_id=self.request_id)
        msg = await self._exchange(data)
        body = msg.body()
        typeid = nodeid_from_binary(body.copy())
        if typeid == _FAULT:
            fault = struct_from_binary(ua.ServiceFault, body)
            raise Fault(fault.ResponseHeader.ServiceResult.value)
        response = struct_from_binary(response_type, body)
        if not response.ResponseHeader.ServiceResult.is_good():
            raise Fault(response.ResponseHeader.ServiceResult.value)
        return response

    async def create_session(
        self,
        *,
        certificate: bytes | None = None,
        endpoint_url: str | None = None,
        application_uri: str = "urn:uacell:test:raw",
        timeout: float = 60000,
    ) -> Session:
        request = ua.CreateSessionRequest()
        p = request.Parameters
        p.ClientDescription = ua.ApplicationDescription(
            ApplicationUri=application_uri,
            ApplicationName=ua.LocalizedText("raw probe"),
            ApplicationType=ua.ApplicationType.Client,
        )
        p.EndpointUrl = self.url if endpoint_url is None else endpoint_url
        p.SessionName = "raw probe"
        p.ClientNonce = os.urandom(32)
        p.ClientCertificate = certificate
        p.RequestedSessionTimeout = timeout
        p.MaxResponseMessageSize = 0
        response = await self.request(request, ua.CreateSessionResponse)
        self.auth = response.Parameters.AuthenticationToken
        return Session(response.Parameters, response.Parameters.AuthenticationToken)

    async def activate_session(
        self, token: Any, session: Session | None = None, user_signature: ua.SignatureData | None = None
    ) -> ua.ActivateSessionResult:
        request = ua.ActivateSessionRequest()
        request.Parameters.UserIdentityToken = token
        if user_signature is not None:
            request.Parameters.UserTokenSignature = user_signature
        request.Parameters.LocaleIds = ["en"]
        if session is not None and self.policy.Mode != ua.MessageSecurityMode.None_:
            data = session.server_certificate + session.nonce
            request.Parameters.ClientSignature.Signature = self.policy.asymmetric_cryptography.signature(data)
            request.Parameters.ClientSignature.Algorithm = self.policy.AsymmetricSignatureURI
        response = await self.request(request, ua.ActivateSessionResponse)
        return response.Parameters

    async def read_value(self, node: ua.NodeId) -> ua.DataValue:
        request = ua.ReadRequest()
        rv = ua.ReadValueId()
        rv.NodeId = node
        rv.AttributeId = ua.AttributeIds.Value
        request.Parameters.NodesToRead = [rv]
        response = await self.request(request, ua.ReadResponse)
        return response.Results[0]

    async def write_value(self, node: ua.NodeId, value: ua.Variant) -> ua.StatusCode:
        request = ua.WriteRequest()
        item = ua.WriteValue()
        item.NodeId = node
        item.AttributeId = ua.AttributeIds.Value
        item.Value = ua.DataValue(value)
        request.Parameters.NodesToWrite = [item]
        response = await self.request(request, ua.WriteResponse)
        return response.Results[0]

    async def call(self, obj: ua.NodeId, method: ua.NodeId, args: list[ua.Variant]) -> ua.CallMethodResult:
        request = ua.CallRequest()
        item = ua.CallMethodRequest()
        item.ObjectId, item.MethodId, item.InputArguments = obj, method, args
        request.Parameters.MethodsToCall = [item]
        response = await self.request(request, ua.CallResponse)
        return response.Results[0]

    async def namespace_index(self, uri: str) -> int:
        dv = await self.read_value(ua.NodeId(ua.ObjectIds.Server_NamespaceArray))
        return list(dv.Value.Value).index(uri)


def anonymous_token(policy_id: str = "anonymous") -> ua.AnonymousIdentityToken:
    return ua.AnonymousIdentityToken(PolicyId=policy_id)


def user_token(
    user: str,
    password: str,
    server_nonce: bytes,
    server_certificate: bytes,
    *,
    algorithm: str = "http://www.w3.org/2001/04/xmlenc#rsa-oaep",
    policy_id: str = "username",
) -> ua.UserNameIdentityToken:
    """A user-name token whose secret (length, password, server nonce) is encrypted for the server."""
    secret = password.encode() + server_nonce
    plain = struct.pack("<I", len(secret)) + secret
    key = uacrypto.x509_from_der(server_certificate).public_key()
    encrypt = {
        "http://www.w3.org/2001/04/xmlenc#rsa-1_5": uacrypto.encrypt_rsa15,
        "http://www.w3.org/2001/04/xmlenc#rsa-oaep": uacrypto.encrypt_rsa_oaep,
        "http://opcfoundation.org/UA/security/rsa-oaep-sha2-256": uacrypto.encrypt_rsa_oaep_sha256,
    }[algorithm]
    return ua.UserNameIdentityToken(
        PolicyId=policy_id, UserName=user, Password=encrypt(key, plain), EncryptionAlgorithm=algorithm
    )


async def none_session(host: str, port: int, **kwargs: Any) -> tuple[RawClient, Session]:
    """Hello, OpenSecureChannel with policy None and CreateSession, all hand-built."""
    raw = await RawClient.connect(host, port, **kwargs)
    try:
        await raw.hello()
        await raw.open_channel()
        session = await raw.create_session()
    except BaseException:
        await raw.close()
        raise
    return raw, session


def _open_parameters(policy: SecurityPolicy, mode: ua.MessageSecurityMode | None) -> ua.OpenSecureChannelParameters:
    params = ua.OpenSecureChannelParameters()
    params.ClientProtocolVersion = 0
    params.RequestType = ua.SecurityTokenRequestType.Issue
    params.SecurityMode = policy.Mode if mode is None else mode
    params.RequestedLifetime = 600000
    params.ClientNonce = os.urandom(policy.secure_channel_nonce_length) or b""
    return params


def _open_message(connection: SecureConnection, params: ua.OpenSecureChannelParameters, request_id: int) -> bytes:
    request = ua.OpenSecureChannelRequest()
    request.Parameters = params
    return connection.message_to_binary(
        struct_to_binary(request), message_type=ua.MessageType.SecureOpen, request_id=request_id
    )


def open_request() -> bytes:
    """The bytes of an OpenSecureChannel request on SecurityPolicy None (request id 1), for a client
    that sends them itself."""
    policy = SecurityPolicyNone()
    return _open_message(SecureConnection(policy, TransportLimits()), _open_parameters(policy, None), 1)
