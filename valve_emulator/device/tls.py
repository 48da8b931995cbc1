"""Modbus/TCP Security (Modbus Organization, 2018): Modbus TCP inside TLS 1.2+, mutual authentication, roles.

A second listener of the same :class:`~valve_emulator.device.server.EmulatorServer` (same units, registers,
tick and checks) whose connections are TLS: the server proves itself with its certificate, the client must
present a certificate signed by the configured CA (no certificate, or one the CA did not sign: the handshake
fails and no Modbus request is ever read), and the client certificate's **role** — the extension
``1.3.6.1.4.1.50316.802.1``, an ASN.1 UTF8String — decides what it may write, through the device's
permission table (:mod:`~valve_emulator.device.roles`): ``viewer`` reads only, ``operator`` writes OP, SP and
the mode, ``instructor`` everything, a custom role of ``device.roles`` the tags it lists.

A certificate whose role is not in the table -- a typo, ``readonly``, or no role extension at all -- gets no
session: the connection is closed right after the handshake, before any request is read, and the refusal is
logged with the client's address, the certificate's subject and the role it claimed (once per client and
cause per interval, :class:`~valve_emulator.device.guard.RefusalLog`). Refused writes name the same three.

A handshake that fails -- no client certificate, one the CA did not sign, TLS 1.1 or older, a client that
stops half-way -- is logged too, with the client's address and OpenSSL's reason (``certificate verify
failed: unable to get local issuer certificate``), once per client and reason per interval: the server runs
the handshake itself (:class:`TlsAcceptor`) rather than inside asyncio's listener, which drops the reason.

The role replaces the plain port's instructor rule (``device.instructor_writes`` / ``instructor_hosts``):
over TLS the certificate, not the IP address, is the credential. TLS 1.0 and 1.1 are refused.
"""

from __future__ import annotations

import asyncio
import ssl
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.x509.oid import ObjectIdentifier

from valve_emulator.device.connection import ModbusConnection
from valve_emulator.device.roles import Role
from valve_emulator.errors import UserError

__all__ = ["ROLE_OID", "server_context", "role_of", "subject_of", "TlsAcceptor", "TlsModbusConnection"]

#: The Modbus/TCP Security role extension.
ROLE_OID = ObjectIdentifier("1.3.6.1.4.1.50316.802.1")
#: The permission of a connection that gets no session (it is closed before any request is read).
_NO_SESSION = Role("(no session)", frozenset())


def server_context(cert: Path | str, key: Path | str, ca: Path | str) -> ssl.SSLContext:
    """A server-side TLS context: TLS 1.2 or later, a client certificate signed by ``ca`` required.

    ``UserError`` naming the file when a certificate, key or CA cannot be loaded."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.verify_mode = ssl.CERT_REQUIRED
    for what, path in (("--tls-cert", cert), ("--tls-key", key), ("--tls-ca", ca)):
        if not Path(path).is_file():
            raise UserError(f"{what} {path}: no such file")
    try:
        ctx.load_cert_chain(str(cert), str(key))
    except (ssl.SSLError, OSError) as exc:
        raise UserError(f"--tls-cert {cert} / --tls-key {key}: cannot load the server certificate and key: "
                        f"{exc}") from None
    try:
        ctx.load_verify_locations(cafile=str(ca))
    except (ssl.SSLError, OSError) as exc:
        raise UserError(f"--tls-ca {ca}: cannot load the CA certificate: {exc}") from None
    return ctx


def role_of(der: bytes | None) -> str | None:
    """The Modbus role of a DER certificate (None: no certificate, or no role extension)."""
    if not der:
        return None
    cert = x509.load_der_x509_certificate(der)
    try:
        ext = cert.extensions.get_extension_for_oid(ROLE_OID)
    except x509.ExtensionNotFound:
        return None
    value = ext.value.value if isinstance(ext.value, x509.UnrecognizedExtension) else b""
    return _utf8_string(value)


def subject_of(der: bytes | None) -> str:
    """The subject of a DER certificate as RFC 4514 text (``CN=plc-7,O=plant``); ``(no certificate)``."""
    if not der:
        return "(no certificate)"
    return x509.load_der_x509_certificate(der).subject.rfc4514_string()


def _utf8_string(der: bytes) -> str | None:
    """Decode a DER UTF8String (tag 0x0C, short or long length form); None when it is not one."""
    if len(der) < 2 or der[0] != 0x0C:
        return None
    length, at = der[1], 2
    if length & 0x80:
        n = length & 0x7F
        length, at = int.from_bytes(der[2:2 + n], "big"), 2 + n
    body = der[at:at + length]
    if len(body) != length:
        return None
    try:
        return body.decode("utf-8")
    except UnicodeDecodeError:
        return None


class TlsModbusConnection(ModbusConnection):
    """A Modbus TCP connection inside TLS: its permission is the client certificate's role, looked up in the
    server's permission table (``server.roles``); a role the table does not have closes the connection."""

    #: the role the certificate claims (None: no role extension), and the certificate's subject
    claimed: str | None = None
    subject: str = ""

    def connection_made(self, transport: Any) -> None:
        ssl_object = transport.get_extra_info("ssl_object")
        der = ssl_object.getpeercert(binary_form=True) if ssl_object is not None else None
        self.claimed, self.subject = role_of(der), subject_of(der)
        super().connection_made(transport)
        if self.slot is None:   # refused at the connection limit
            return
        server = self.server
        server.tls_sessions += 1   # only after a complete handshake: a refused client never gets here
        self.who = f"{self.peer_ip} (certificate {self.subject}, role {self.claimed!r})"
        if server.roles.get(self.claimed) is None:
            server.tls_refused += 1
            why = "carries no role" if self.claimed is None else f"claims role {self.claimed!r}"
            server.refusals.note(self.peer_ip, ("tls session", self.subject, self.claimed),
                                 "refused TLS session from %s: certificate %s %s, which is not in the permission "
                                 "table (%s; device.roles adds custom roles); connection closed",
                                 self.peer_ip, self.subject, why, server.roles.describe())
            self._close_now()

    def permission(self) -> Role:
        return self.server.roles.get(self.claimed) or _NO_SESSION

    def eof_received(self) -> bool:
        # TLS cannot stay half-open (asyncio closes the transport after the peer's close_notify whatever we
        # answer, and warns when we ask to keep it): do the plain connection's bookkeeping, then say so.
        super().eof_received()
        return False


class TlsAcceptor(asyncio.Protocol):
    """A TCP connection of the TLS listener until its handshake is done: runs the handshake
    (``loop.start_tls``, within ``device.frame_timeout``), then hands the TLS transport to a
    :class:`TlsModbusConnection`; a failed handshake is counted (``server.tls_failed``), logged with the
    client's address and the reason, and the connection aborted."""

    def __init__(self, server: Any, context: ssl.SSLContext) -> None:
        self.server, self.context = server, context

    def connection_made(self, transport: Any) -> None:
        transport.pause_reading()   # the ClientHello stays in the socket until start_tls reads it
        task = asyncio.get_running_loop().create_task(self._handshake(transport), name="valve-emulator-tls")
        self.server.tls_handshakes.add(task)
        task.add_done_callback(self.server.tls_handshakes.discard)

    async def _handshake(self, transport: Any) -> None:
        server, conn = self.server, TlsModbusConnection(self.server)
        peer = transport.get_extra_info("peername")
        ip = peer[0] if peer else "?"
        try:
            tls = await asyncio.get_running_loop().start_tls(transport, conn, self.context, server_side=True,
                                                              ssl_handshake_timeout=server.guard.frame_timeout)
        except asyncio.CancelledError:   # the server is stopping
            transport.abort()
            raise
        except Exception as exc:   # an SSLError or OSError mostly; whatever it is, this connection is over
            transport.abort()
            server.tls_failed += 1
            reason = _handshake_reason(exc)
            server.refusals.note(ip, ("tls handshake", reason), "refused TLS handshake from %s: %s", ip, reason)
            return
        conn.connection_made(tls)


def _handshake_reason(exc: BaseException) -> str:
    """What went wrong in a handshake, in OpenSSL's words where it has some."""
    if isinstance(exc, ssl.SSLCertVerificationError):
        return f"certificate verify failed: {exc.verify_message} (a client certificate the --tls-ca CA did not sign?)"
    if isinstance(exc, ssl.SSLError):
        reason = exc.reason or str(exc)
        hint = {"PEER_DID_NOT_RETURN_A_CERTIFICATE": " (the client sent no certificate)",
                "UNSUPPORTED_PROTOCOL": " (TLS 1.2 or later is required)",
                "NO_SHARED_CIPHER": " (TLS 1.2 or later is required)"}.get(reason, "")
        return f"{reason}{hint}"
    if isinstance(exc, TimeoutError) or "taking longer" in str(exc):
        return "handshake not completed within device.frame_timeout"
    return f"connection lost during the handshake ({exc.__class__.__name__}: {exc})"
