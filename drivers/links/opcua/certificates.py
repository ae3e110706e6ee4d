"""The OPC UA server's own certificate, and which client certificates it accepts.

The server's key and self-signed certificate are made in ``pki_dir`` at the first start (the key
readable by its owner only). A client's certificate must be in ``<pki_dir>/trusted`` (read at
every connection, so one copied there counts at once) unless the station file trusts every
client; a refused one is kept in ``<pki_dir>/rejected`` under its SHA-1, and the refusal is
logged and reported with the path to move it to.
"""

from __future__ import annotations

import hashlib
import logging
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

from .access import default_pki_dir
from .settings import OpcUaLinkConfig

log = logging.getLogger(__name__)
_UA: Any = ua  # asyncua's stubs are strict about StatusCode


async def make_certificate(config: OpcUaLinkConfig) -> Path:
    """The server's key and self-signed certificate in the PKI folder (made at the first
    start), with its ``trusted`` and ``rejected`` folders; returns the folder."""
    pki = Path(config.pki_dir) if config.pki_dir else default_pki_dir()
    for sub in ("", "trusted", "rejected"):
        (pki / sub).mkdir(parents=True, exist_ok=True)
    key, cert = pki / "server_key.pem", pki / "server_cert.der"
    await setup_self_signed_certificate(
        key, cert, config.application_uri, socket.gethostname(),
        [ExtendedKeyUsageOID.SERVER_AUTH],
        {"commonName": "mvpose station", "organizationName": "mvpose"})
    key.chmod(0o600)
    return pki


async def validate_clients(server: Server, pki: Path, trust_all: bool,
                           refused: Callable[[str], None]) -> None:
    """Load the server's certificate and key from ``pki`` and judge each client's certificate
    (``refused`` hears why one was not accepted)."""
    key, cert = pki / "server_key.pem", pki / "server_cert.der"
    await server.load_certificate(str(cert))
    await server.load_private_key(str(key))
    store: TrustStore | None
    if trust_all:
        options = CertificateValidatorOptions.BASIC_VALIDATION
        store = None
    else:
        options = (CertificateValidatorOptions.TRUSTED_VALIDATION
                   | CertificateValidatorOptions.PEER_CLIENT)
        store = TrustStore([pki / "trusted"], [])
    checker = CertificateValidator(options, store)
    rejected = pki / "rejected"

    async def validate(certificate: x509.Certificate, app: ua.ApplicationDescription) -> None:
        if store is not None:
            await store.load_trust()  # a certificate copied into trusted/ counts at once
        try:
            await checker.validate(certificate, app)
        except ServiceError as err:
            der = certificate.public_bytes(Encoding.DER)
            kept = rejected / f"{hashlib.sha1(der).hexdigest()}.der"  # noqa: S324 - a name
            kept.write_bytes(der)
            text = (f"client certificate of {app.ApplicationUri!r} refused "
                    f"({_UA.StatusCode(err.code).name}); kept as {kept}: move it to "
                    f"{pki / 'trusted'} to trust it")
            log.warning("OPC UA: %s", text)
            refused(text)
            raise

    server.set_certificate_validator(validate)
