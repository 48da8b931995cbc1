"""Modbus/TCP Security (Modbus Organization, 2018): Modbus TCP inside TLS 1.2+, mutual authentication, roles.

A second listener of the same :class:`~valve_emulator.device.server.EmulatorServer` (same units, registers,
tick and checks) whose connections are TLS: the server proves itself with its certificate, the client must
present a certificate signed by the configured CA (no certificate, or one the CA did not sign: the handshake
fails and no Modbus request is ever read), and the client certificate's **role** — the extension
``1.3.6.1.4.1.50316.802.1``, an ASN.1 UTF8String — decides what it may write:

- ``instructor``: everything, including the instructor registers (S, J, load, noise, fault, comm faults);
- ``operator``, another role, or no role: what a Modbus client without instructor permission may write.

The role replaces the plain port's instructor rule (``device.instructor_writes`` / ``instructor_hosts``):
over TLS the certificate, not the IP address, is the credential. TLS 1.0 and 1.1 are refused.
"""

from __future__ import annotations

import ssl
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.x509.oid import ObjectIdentifier

from valve_emulator.device.connection import ModbusConnection
from valve_emulator.errors import UserError

__all__ = ["ROLE_OID", "INSTRUCTOR", "OPERATOR", "server_context", "role_of", "TlsModbusConnection"]

#: The Modbus/TCP Security role extension.
ROLE_OID = ObjectIdentifier("1.3.6.1.4.1.50316.802.1")
INSTRUCTOR = "instructor"
OPERATOR = "operator"


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
    """A Modbus TCP connection inside TLS: instructor permission from the client certificate's role."""

    role: str | None = None

    def connection_made(self, transport: Any) -> None:
        super().connection_made(transport)
        self.server.tls_sessions += 1   # only after a complete handshake: a refused client never gets here
        ssl_object = transport.get_extra_info("ssl_object")
        self.role = role_of(ssl_object.getpeercert(binary_form=True)) if ssl_object is not None else None
        self.instructor = self.permission()

    def permission(self) -> bool:
        return self.role == INSTRUCTOR

    def eof_received(self) -> bool:
        # TLS cannot stay half-open (asyncio closes the transport after the peer's close_notify whatever we
        # answer, and warns when we ask to keep it): do the plain connection's bookkeeping, then say so.
        super().eof_received()
        return False
