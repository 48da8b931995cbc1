"""Certificates for the secure interfaces, made with the ``cryptography`` package (``valve-emulator certs``).

- :func:`opcua_certificate`: a self-signed OPC UA *application instance certificate* whose SubjectAltName
  URI is the server's ApplicationUri (clients refuse a certificate whose URI differs), with the DNS names
  and IP addresses it is reached at, and the key usages OPC UA Part 6 §6.2.2 asks for.
- :func:`modbus_ca`, :func:`modbus_certificate`: a test CA for Modbus/TCP Security and the server's and
  clients' certificates it signs; a client certificate carries its role in the extension
  ``1.3.6.1.4.1.50316.802.1`` as a DER UTF8String (:mod:`~valve_emulator.device.tls`).

Keys are RSA 2048 (what Basic256Sha256 requires); private keys are written unencrypted with mode 0600, for
tests and isolated training networks. A production deployment uses its own PKI.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import os
from collections.abc import Sequence
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from valve_emulator.device.tls import ROLE_OID

__all__ = ["opcua_certificate", "modbus_ca", "modbus_certificate", "role_extension"]

VALID_DAYS = 3650


def _key() -> rsa.RSAPrivateKey:
    return rsa.generate_private_key(public_exponent=65537, key_size=2048)


def _names(hosts: Sequence[str]) -> list[x509.GeneralName]:
    out: list[x509.GeneralName] = []
    for host in hosts:
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            out.append(x509.DNSName(host))
    return out


def _write_key(key: rsa.RSAPrivateKey, path: Path) -> None:
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.TraditionalOpenSSL,
                             serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _builder(subject: str, issuer: x509.Name | None, public_key) -> x509.CertificateBuilder:
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject),
                      x509.NameAttribute(NameOID.ORGANIZATION_NAME, "valve_emulator")])
    now = _dt.datetime.now(_dt.UTC)
    return (x509.CertificateBuilder().subject_name(name).issuer_name(issuer or name).public_key(public_key)
            .serial_number(x509.random_serial_number()).not_valid_before(now - _dt.timedelta(minutes=5))
            .not_valid_after(now + _dt.timedelta(days=VALID_DAYS)))


def opcua_certificate(directory: Path | str, *, application_uri: str, hosts: Sequence[str] = ("localhost",
                      "127.0.0.1"), name: str = "server") -> tuple[Path, Path]:
    """Write ``NAME.der`` (the certificate, DER as OPC UA exchanges it) and ``NAME-key.pem``; return both paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    key = _key()
    cert = (_builder(f"valve_emulator OPC UA {name}", None, key.public_key())
            .add_extension(x509.SubjectAlternativeName([x509.UniformResourceIdentifier(application_uri),
                                                        *_names(hosts)]), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=True, key_encipherment=True,
                                         data_encipherment=True, key_agreement=False, key_cert_sign=True,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    cert_path, key_path = directory / f"{name}.der", directory / f"{name}-key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.DER))
    _write_key(key, key_path)
    return cert_path, key_path


def role_extension(role: str) -> x509.UnrecognizedExtension:
    """The Modbus/TCP Security role extension holding ``role`` as a DER UTF8String."""
    body = role.encode("utf-8")
    if len(body) < 128:
        length = bytes([len(body)])
    else:
        n = (len(body).bit_length() + 7) // 8
        length = bytes([0x80 | n]) + len(body).to_bytes(n, "big")
    return x509.UnrecognizedExtension(ROLE_OID, b"\x0c" + length + body)


def modbus_ca(directory: Path | str) -> tuple[Path, Path]:
    """Write (or keep, if both exist) ``ca.pem`` and ``ca-key.pem``: a self-signed test CA."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = directory / "ca.pem", directory / "ca-key.pem"
    if cert_path.exists() and key_path.exists():
        return cert_path, key_path
    key = _key()
    cert = (_builder("valve_emulator test CA", None, key.public_key())
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(key, key_path)
    return cert_path, key_path


def modbus_certificate(directory: Path | str, name: str, *, role: str | None = None, server: bool = False,
                       hosts: Sequence[str] = ("localhost", "127.0.0.1")) -> tuple[Path, Path]:
    """Write ``NAME.pem`` and ``NAME-key.pem`` signed by the CA in ``directory`` (made if missing): a server
    certificate for ``hosts``, or a client certificate with the Modbus ``role``."""
    directory = Path(directory)
    ca_cert_path, ca_key_path = modbus_ca(directory)
    ca_cert = x509.load_pem_x509_certificate(ca_cert_path.read_bytes())
    ca_key = serialization.load_pem_private_key(ca_key_path.read_bytes(), password=None)
    key = _key()
    usage = ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH
    builder = (_builder(name, ca_cert.subject, key.public_key())
               .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
               .add_extension(x509.ExtendedKeyUsage([usage]), critical=False))
    if server:
        builder = builder.add_extension(x509.SubjectAlternativeName(_names(hosts)), critical=False)
    if role is not None:
        builder = builder.add_extension(role_extension(role), critical=False)
    cert = builder.sign(ca_key, hashes.SHA256())
    cert_path, key_path = directory / f"{name}.pem", directory / f"{name}-key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(key, key_path)
    return cert_path, key_path
