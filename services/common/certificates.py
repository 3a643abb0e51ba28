"""The lab's credentials for a secured bus (``dammrl bus init``, and each ``dammrl up``'s
own): a CA and one certificate per role (``services.common.security.ROLES``), as rustls
accepts them. Apart from ``security`` so that a session that only *uses* credentials
(``dammrl stop``) does not load the X.509 library."""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from collections.abc import Iterable
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from services.common.security import CA_FILE, ROLES

VALID_DAYS = 825


def create_credentials(out: Path, hosts: Iterable[str] = (), roles: Iterable[str] = ROLES) -> None:
    """A lab CA and one certificate per role in ``out`` (keys 0600, the folder 0700).

    Each certificate names ``localhost``, 127.0.0.1 and ``hosts`` (the addresses or names
    the services listen on when they run on separate machines).
    """
    out.mkdir(parents=True, exist_ok=True)
    out.chmod(0o700)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = _certificate("dammrl lab CA", ca_key, ca_key, None, [])
    (out / CA_FILE).write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    names = ["localhost", "127.0.0.1", *hosts]
    for role in roles:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _certificate(role, key, ca_key, ca, names)
        _write_key(out / f"{role}.key", key)
        (out / f"{role}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _certificate(
    common_name: str,
    key: ec.EllipticCurvePrivateKey,
    issuer_key: ec.EllipticCurvePrivateKey,
    issuer: x509.Certificate | None,
    names: list[str],
) -> x509.Certificate:
    """The CA (``issuer`` None) or a role's certificate, as rustls accepts them."""
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    now = dt.datetime.now(dt.UTC)
    is_ca = issuer is None
    builder = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject if issuer is None else issuer.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS * (4 if is_ca else 1)))
        .add_extension(x509.BasicConstraints(ca=is_ca, path_length=0 if is_ca else None), True)
        .add_extension(_key_usage(is_ca), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), False)
    )
    if not is_ca:
        usages = [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
        builder = builder.add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        builder = builder.add_extension(x509.SubjectAlternativeName(_alt_names(names)), False)
    return builder.sign(issuer_key, hashes.SHA256())


def _key_usage(is_ca: bool) -> x509.KeyUsage:
    return x509.KeyUsage(
        digital_signature=True, key_cert_sign=is_ca, crl_sign=is_ca, content_commitment=False,
        key_encipherment=False, data_encipherment=False, key_agreement=False,
        encipher_only=False, decipher_only=False,
    )  # fmt: skip


def _alt_names(names: list[str]) -> list[x509.GeneralName]:
    """rustls checks the peer's name against these only (never the Common Name)."""
    alt: list[x509.GeneralName] = []
    for name in dict.fromkeys(names):
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            alt.append(x509.DNSName(name))
    return alt


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "wb") as handle:
        handle.write(pem)
