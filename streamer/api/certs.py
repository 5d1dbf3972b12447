"""A small certificate authority for a cell: one CA, and certificates for a service and its clients.

`init_certs` (`pvt certs init DIR`) makes an EC P-256 CA and one certificate per identity (service,
operator, observer by default). With mutual TLS the service reads the client certificate's CN, the
subject the access rules grant a role to (streamer/api/security.py), so the CN is the identity and names
the files. Every certificate carries 127.0.0.1, ::1, `localhost` and any `hosts` as alternative names,
and both server and client key usage (a service may dial a router). Keys are unencrypted PKCS#8 PEM,
mode 0600 (Zenoh reads them without a passphrase). For tests and first setups; docs/security.md says how
to use your own CA.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

CA_NAME = "pvt-ca"
# identity -> certificate common name: the names the default [security] roles refer to
DEFAULT_IDENTITIES: dict[str, str] = {
    "service": "pvt-service",
    "operator": "pvt-operator",
    "observer": "pvt-observer",
}
LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")


class CertError(Exception):
    """A certificate could not be made or written; `code` is machine-readable, `path` names the file."""

    def __init__(self, code: str, message: str, *, path: str = ""):
        super().__init__(message)
        self.code = code
        self.message = message
        self.path = path


@dataclass(frozen=True)
class Identity:
    """The files of one identity: its certificate and private key (PEM)."""

    name: str  # file stem: service, operator, observer, ...
    common_name: str
    certificate: Path
    private_key: Path


@dataclass(frozen=True)
class CertSet:
    """What `init_certs` wrote: the CA and one `Identity` per name."""

    directory: Path
    ca_certificate: Path
    ca_private_key: Path
    identities: dict[str, Identity]

    def __getitem__(self, name: str) -> Identity:
        return self.identities[name]


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "pvt"),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def _san(hosts: Sequence[str]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for host in dict.fromkeys([*LOOPBACK_HOSTS, *hosts]):  # ordered, without duplicates
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            if not host or any(c.isspace() or c in "/:@" for c in host):
                raise CertError("CERT_HOST", f"host {host!r} is neither an IP address nor a DNS name",
                                path="hosts") from None
            names.append(x509.DNSName(host))
    return x509.SubjectAlternativeName(names)


def make_ca(
    common_name: str = CA_NAME, *, days: int = 825, now: dt.datetime | None = None
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A self-signed CA (basic constraints CA, path length 0: it signs end-entity certificates only)."""
    key = _key()
    start = (now or dt.datetime.now(dt.UTC)) - dt.timedelta(minutes=5)  # tolerate small clock skew
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(_name(common_name))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(start + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True, crl_sign=True,
                encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def make_certificate(
    ca_key: ec.EllipticCurvePrivateKey,
    ca_cert: x509.Certificate,
    common_name: str,
    *,
    hosts: Sequence[str] = (),
    days: int = 825,
    now: dt.datetime | None = None,
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """An end-entity certificate for `common_name`, signed by the CA, usable as TLS server and client."""
    if not common_name or len(common_name) > 64:
        raise CertError("CERT_NAME", f"common name {common_name!r} must be 1-64 characters", path="name")
    key = _key()
    start = (now or dt.datetime.now(dt.UTC)) - dt.timedelta(minutes=5)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(start + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=False, crl_sign=False,
                encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(_san(hosts), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    return key, cert


def _write(path: Path, data: bytes, *, private: bool) -> None:
    # create with the final mode: a private key is never readable by others, not even briefly
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
    fd = os.open(path, flags, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    if private:
        os.chmod(path, 0o600)  # an existing file keeps its mode on O_TRUNC


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def init_certs(
    directory: str | os.PathLike[str],
    *,
    identities: dict[str, str] | None = None,
    hosts: Sequence[str] = (),
    days: int = 825,
    ca_name: str = CA_NAME,
    force: bool = False,
) -> CertSet:
    """Make a CA and one certificate per identity in `directory`: ca.pem, ca.key, <name>.pem, <name>.key.

    `identities` maps a file stem to a common name (default: service, operator, observer as
    pvt-service, pvt-operator, pvt-observer). Refuses to overwrite existing files unless `force`.
    """
    ids = dict(DEFAULT_IDENTITIES if identities is None else identities)
    if not ids:
        raise CertError("CERT_NAME", "at least one identity is needed", path="identities")
    for stem in ids:
        if not stem or stem == "ca" or any(c in stem for c in "/\\.") or stem != stem.strip():
            raise CertError("CERT_NAME", f"identity name {stem!r} is not a plain file name (and not 'ca')",
                            path="identities")
    if not 1 <= days <= 3650:
        raise CertError("CERT_DAYS", f"days must be 1..3650, got {days}", path="days")
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    targets = [out / "ca.pem", out / "ca.key"] + [out / f"{s}.{ext}" for s in ids for ext in ("pem", "key")]
    existing = [str(p) for p in targets if p.exists()]
    if existing and not force:
        raise CertError("CERT_EXISTS", f"{', '.join(existing)} already exist(s); use force to replace",
                        path=existing[0])
    ca_key, ca_cert = make_ca(ca_name, days=days)
    _write(out / "ca.key", _key_pem(ca_key), private=True)
    _write(out / "ca.pem", _cert_pem(ca_cert), private=False)
    made = {}
    for stem, cn in ids.items():
        key, cert = make_certificate(ca_key, ca_cert, cn, hosts=hosts, days=days)
        _write(out / f"{stem}.key", _key_pem(key), private=True)
        _write(out / f"{stem}.pem", _cert_pem(cert), private=False)
        made[stem] = Identity(stem, cn, out / f"{stem}.pem", out / f"{stem}.key")
    return CertSet(out, out / "ca.pem", out / "ca.key", made)


def common_name(certificate: str | os.PathLike[str]) -> str:
    """The subject common name of a PEM certificate file (the identity the access rules see)."""
    cert = x509.load_pem_x509_certificate(Path(certificate).read_bytes())
    attrs = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    value = attrs[0].value if attrs else ""
    return value if isinstance(value, str) else value.decode()
