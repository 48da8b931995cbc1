"""Which OPC UA client certificates the server accepts: a trust list on disk, as UaExpert and opc-plc keep one.

A secure OPC UA connection (Sign or Sign&Encrypt) begins with the client presenting its application instance
certificate. The server accepts it only when the certificate is in the trust list -- a folder of
certificates -- or was issued by a CA certificate in it::

    PKI/
    ├── trusted/certs/    certificates (DER or PEM) this server accepts; a CA here admits what it signed
    └── rejected/certs/   certificates it refused, one file each, named "<CN> [<SHA-1 thumbprint>].der"

An unknown client certificate is copied to ``rejected/certs`` and the session is refused with
``BadCertificateUntrusted``; the refusal is logged with the certificate's subject, its ApplicationUri and
the file it was copied to (once per certificate per interval, so a client retrying in a loop does not fill
the log). To let the client in, move its file from ``rejected/certs`` to ``trusted/certs``: the trust list
is read again at every session, so no restart is needed. This is the OPC UA Part 12 "directory store"
layout (``certs`` folders), the one UaExpert, opc-plc and the OPC Foundation's .NET stack use.

``trust_all`` accepts every certificate without a trust list (the client still needs a certificate, and a
secure policy still encrypts); the server allows it only on a loopback address (``--opcua-trust-all``).
Before the trust list, asyncua's basic checks run: the certificate is within its validity period and its
SubjectAltName URI is the client's ApplicationUri.
"""

from __future__ import annotations

import hashlib
import logging
import re
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization

from valve_emulator.device.guard import RefusalLog

__all__ = ["TrustList"]

_log = logging.getLogger(__name__)
_SUFFIXES = (".der", ".pem", ".crt", ".cer")


def thumbprint(cert: x509.Certificate) -> str:
    """The SHA-1 thumbprint OPC UA tools show (upper-case hex of the DER)."""
    return hashlib.sha1(cert.public_bytes(serialization.Encoding.DER)).hexdigest().upper()


def common_name(cert: x509.Certificate) -> str:
    names = cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)
    return str(names[0].value) if names else cert.subject.rfc4514_string()


def _load(path: Path) -> x509.Certificate | None:
    """The certificate in ``path`` (DER or PEM); None for a file that is not one (logged, then skipped)."""
    data = path.read_bytes()
    try:
        if b"-----BEGIN CERTIFICATE-----" in data:
            return x509.load_pem_x509_certificate(data)
        return x509.load_der_x509_certificate(data)
    except ValueError:
        _log.warning("OPC UA trust list: %s is not a certificate; skipped", path)
        return None


def _issued_by(cert: x509.Certificate, ca: x509.Certificate) -> bool:
    """Is ``cert`` signed by ``ca``, a CA certificate (BasicConstraints ca=true)?"""
    try:
        if not ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca:
            return False
        cert.verify_directly_issued_by(ca)
    except (x509.ExtensionNotFound, InvalidSignature, ValueError, TypeError):
        return False
    return True


class TrustList:
    """The trust list in ``root`` (``trusted/certs``, ``rejected/certs``, made when missing), as an asyncua
    certificate validator: ``server.set_certificate_validator(trust_list)``.

    ``trust_all``: accept every client certificate (loopback only, checked by
    :meth:`~valve_emulator.opcua.server.OpcUaSecurity.check`); nothing is then written.
    Counters: :attr:`accepted`, :attr:`refused`.
    """

    def __init__(self, root: Path | str | None, *, trust_all: bool = False) -> None:
        self.root = None if root is None else Path(root)
        self.trust_all = trust_all
        self.accepted = 0
        self.refused = 0
        self._basic = CertificateValidator(CertificateValidatorOptions.BASIC_VALIDATION
                                           | CertificateValidatorOptions.PEER_CLIENT)
        self._refusals = RefusalLog(_log)

    @property
    def trusted(self) -> Path:
        return self._folder("trusted")

    @property
    def rejected(self) -> Path:
        return self._folder("rejected")

    def _folder(self, name: str) -> Path:
        if self.root is None:
            raise ValueError("a trust list without a folder (trust_all) has no trusted or rejected certificates")
        return self.root / name / "certs"

    def create(self) -> None:
        """Make ``trusted/certs`` and ``rejected/certs`` (an ``OSError`` names the folder)."""
        if self.root is not None:
            for folder in (self.trusted, self.rejected):
                folder.mkdir(parents=True, exist_ok=True)

    def trusted_certificates(self) -> list[x509.Certificate]:
        """Every certificate under ``trusted`` (read now: a file moved there counts at the next session)."""
        if self.root is None or not (self.root / "trusted").is_dir():
            return []
        files = sorted(p for p in (self.root / "trusted").rglob("*") if p.suffix.lower() in _SUFFIXES)
        return [cert for cert in map(_load, files) if cert is not None]

    def is_trusted(self, cert: x509.Certificate) -> bool:
        """Is ``cert`` in the trust list, or issued by a CA certificate in it?"""
        der = cert.public_bytes(serialization.Encoding.DER)
        for known in self.trusted_certificates():
            if known.public_bytes(serialization.Encoding.DER) == der or _issued_by(cert, known):
                return True
        return False

    def reject(self, cert: x509.Certificate) -> Path:
        """Copy ``cert`` to ``rejected/certs`` (DER, named after its CN and thumbprint); its path."""
        self.rejected.mkdir(parents=True, exist_ok=True)
        name = re.sub(r"[^A-Za-z0-9 ._-]", "_", common_name(cert))[:64].strip() or "certificate"
        path = self.rejected / f"{name} [{thumbprint(cert)}].der"
        path.write_bytes(cert.public_bytes(serialization.Encoding.DER))
        return path

    async def __call__(self, cert: x509.Certificate, app_description: Any) -> None:
        """asyncua's validator call at CreateSession: return to accept, raise ``ServiceError`` to refuse."""
        uri = getattr(app_description, "ApplicationUri", None) or "(no ApplicationUri)"
        try:
            await self._basic.validate(cert, app_description)
        except ServiceError as exc:
            self._refuse(cert, uri, ua.StatusCode(exc.code).name, "its validity period or SubjectAltName URI "
                         "does not fit")
            raise
        if self.trust_all or self.is_trusted(cert):
            self.accepted += 1
            return
        path = self.reject(cert)
        self._refuse(cert, uri, "BadCertificateUntrusted", f"not in the trust list {self.trusted}; copied to "
                     f"{path} (move it to {self.trusted} to trust it)")
        raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)

    def _refuse(self, cert: x509.Certificate, uri: str, status: str, why: str) -> None:
        self.refused += 1
        self._refusals.note(uri, (thumbprint(cert), status), "refused OPC UA session of client %s (certificate "
                            "%s, thumbprint %s): %s, %s", uri, cert.subject.rfc4514_string(), thumbprint(cert),
                            status, why)
