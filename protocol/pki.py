"""The swarm's certificates: one CA per swarm, one certificate per robot, one for the monitor.

::

    ca = create_ca(out / "ca", "lab")                    # ca/ca.pem, ca/ca.key (keep ca/ private)
    issue(ca, robot_name(3), out / "robot3" / "tls")      # tls/ca.pem, tls/cert.pem, tls/key.pem
    issue(ca, MONITOR_NAME, out / "monitor")              # what `dinerf-agent status` presents
    info = describe(out / "robot3" / "tls" / "cert.pem")  # CertInfo(common_name='robot-3', ...)

Why this shape:

- The common name (CN) is the identity: Zenoh's access control matches a link's peer by the CN
  of the certificate it presented (``protocol.acl``), so robot 3 is ``robot-3`` whatever
  address it connects from. Certificates also name ``localhost`` and ``127.0.0.1``, but the
  generated swarm files do not ask Zenoh to check names against addresses: robots move between
  networks, and an address says nothing the CA-signed CN does not.
- One CA per swarm, created with the swarm: a certificate of another swarm, or self-signed,
  fails the TLS handshake (mutual TLS: both ends must chain to this CA).
- The CA key never goes into a robot folder; ``issue`` copies only the CA *certificate*. Whoever
  holds ``ca.key`` can mint robots, so it stays with the operator (``<out>/ca/`` by default).
- ECDSA P-256 keys: small, quick to make (a swarm's PKI takes milliseconds), supported by rustls.
- Every certificate issued is recorded in ``<ca>/issued.json`` (serial, CN, expiry, SHA-256
  fingerprint): what was handed out is on record when one must be revoked.

Revocation is not here: Zenoh's TLS has no CRL, so a revoked robot is denied by name in the
access control every robot loads (``protocol.acl``, ``[security] revoked``). Pure Python (the
``cryptography`` package): no zenoh, no torch.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

#: File names inside a CA folder and inside a certificate folder (a robot's ``tls/``, the monitor's).
CA_CERT, CA_KEY, ISSUED = "ca.pem", "ca.key", "issued.json"
CERT, KEY = "cert.pem", "key.pem"
#: The CN of the monitor certificate (`dinerf-agent status`): may subscribe and query, never speak.
MONITOR_NAME = "monitor"
_ROBOT_RE = re.compile(r"robot-(0|[1-9][0-9]{0,9})")


class PkiError(ValueError):
    """A certificate or key that is missing, unreadable, or not what it must be."""


@dataclass
class SecurityConfig:
    """``[security]`` of swarm.toml / scenario.toml: whether and how links are authenticated."""

    #: plain tcp/, anyone who reaches a port is admitted (only for closed test networks)
    insecure: bool = False
    #: a robot's certificate folder (ca.pem, cert.pem, key.pem), relative to its data folder
    tls_dir: str = "tls"
    #: the monitor's certificate folder, relative to the swarm file
    monitor_dir: str = "monitor"
    #: identities denied by every robot's access control, e.g. ["robot-3"] (see `dinerf-agent cert revoke`)
    revoked: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        for name in self.revoked:
            if not isinstance(name, str) or not (_ROBOT_RE.fullmatch(name) or name == MONITOR_NAME):
                raise ValueError(f"security.revoked: {name!r} is not an identity (robot-<id> or {MONITOR_NAME!r})")


@dataclass(frozen=True)
class CertInfo:
    common_name: str
    serial: int
    not_after: str  # ISO 8601, UTC
    issuer: str
    fingerprint: str  # SHA-256 of the DER, hex


def robot_name(robot_id: int) -> str:
    """The CN of robot ``robot_id``'s certificate."""
    if type(robot_id) is not int or robot_id < 0:
        raise ValueError(f"robot id must be a non-negative integer, got {robot_id!r}")
    return f"robot-{robot_id}"


def robot_id_of(common_name: str) -> int | None:
    """The robot id a CN stands for (None for the monitor or anything else)."""
    m = _ROBOT_RE.fullmatch(common_name)
    return int(m[1]) if m else None


def _now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _write_private(path: Path, data: bytes) -> None:
    """Write a key readable by its owner only (created 0600, never world-readable for an instant)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    # PKCS#8: the form rustls (Zenoh's TLS) reads
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def create_ca(ca_dir: Path, swarm: str, days: int = 3650, overwrite: bool = False) -> Path:
    """A new CA for ``swarm`` in ``ca_dir`` (ca.pem, ca.key); returns ``ca_dir``."""
    ca_dir = Path(ca_dir)
    if (ca_dir / CA_KEY).exists() and not overwrite:
        raise PkiError(f"{ca_dir / CA_KEY} exists: a swarm keeps its CA (use a new folder, or overwrite)")
    key = ec.generate_private_key(ec.SECP256R1())
    now = _now()
    subject = _name(f"dinerf swarm {swarm} CA")
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    _write_private(ca_dir / CA_KEY, _key_pem(key))
    (ca_dir / CA_CERT).write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (ca_dir / ISSUED).write_text("[]\n")
    return ca_dir


def _load_ca(ca_dir: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    ca_dir = Path(ca_dir)
    for name in (CA_CERT, CA_KEY):
        if not (ca_dir / name).is_file():
            raise PkiError(f"{ca_dir}: no {name} (a CA folder written by `dinerf-agent split`)")
    try:
        cert = x509.load_pem_x509_certificate((ca_dir / CA_CERT).read_bytes())
        key = serialization.load_pem_private_key((ca_dir / CA_KEY).read_bytes(), password=None)
    except (ValueError, TypeError) as e:
        raise PkiError(f"{ca_dir}: unreadable CA certificate or key ({e})") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey) or key.public_key() != cert.public_key():
        raise PkiError(f"{ca_dir}: {CA_KEY} is not the key of {CA_CERT}")
    return cert, key


def issue(ca_dir: Path, common_name: str, out_dir: Path, hosts: tuple[str, ...] = (), days: int = 3650) -> Path:
    """A certificate for ``common_name`` signed by the CA in ``ca_dir``, written to ``out_dir``
    (ca.pem: the CA's certificate, cert.pem, key.pem); returns ``out_dir``.

    ``hosts`` (names or IP addresses) join localhost/127.0.0.1 as subject alternative names,
    for a swarm that checks names on connect (``tls_verify_name_on_connect``).
    """
    if not (robot_id_of(common_name) is not None or common_name == MONITOR_NAME):
        raise PkiError(f"{common_name!r} is not an identity of a swarm (robot-<id> or {MONITOR_NAME!r})")
    ca_cert, ca_key = _load_ca(ca_dir)
    key = ec.generate_private_key(ec.SECP256R1())
    now = _now()
    cert = (x509.CertificateBuilder().subject_name(_name(common_name)).issuer_name(ca_cert.subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.SubjectAlternativeName(_alt_names(hosts)), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    out_dir = Path(out_dir)
    _write_private(out_dir / KEY, _key_pem(key))
    (out_dir / CERT).write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (out_dir / CA_CERT).write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))
    _record(Path(ca_dir), _info(cert))
    return out_dir


def _alt_names(hosts: tuple[str, ...]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    return names


def _record(ca_dir: Path, info: CertInfo) -> None:
    path = ca_dir / ISSUED
    try:
        issued = json.loads(path.read_text()) if path.is_file() else []
    except json.JSONDecodeError:
        raise PkiError(f"{path}: not JSON; fix or remove it") from None
    issued.append(info.__dict__)
    path.write_text(json.dumps(issued, indent=1) + "\n")


def _info(cert: x509.Certificate) -> CertInfo:
    cns = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return CertInfo(common_name=str(cns[0].value) if cns else "", serial=cert.serial_number,
                    not_after=cert.not_valid_after_utc.isoformat(), issuer=cert.issuer.rfc4514_string(),
                    fingerprint=cert.fingerprint(hashes.SHA256()).hex())


def _load_cert(path: Path) -> x509.Certificate:
    path = Path(path)
    if not path.is_file():
        raise PkiError(f"no certificate {path}")
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except ValueError as e:
        raise PkiError(f"{path}: not a PEM certificate ({e})") from None


def describe(cert_path: Path) -> CertInfo:
    """CN, serial, expiry, issuer and fingerprint of a PEM certificate."""
    return _info(_load_cert(cert_path))


def check_identity(tls_dir: Path, common_name: str) -> CertInfo:
    """Check a certificate folder before a session opens: the three files are there, the key is the
    certificate's, the certificate is signed by ``ca.pem``, is valid now, and is ``common_name``'s.
    Raises PkiError saying what is wrong (a robot started with another's folder would otherwise
    open a session whose every message the access control silently denies)."""
    tls_dir = Path(tls_dir)
    for name in (CA_CERT, CERT, KEY):
        if not (tls_dir / name).is_file():
            raise PkiError(f"{tls_dir}: no {name} (certificates are written by `dinerf-agent split` or "
                           "`dinerf-agent cert issue`)")
    ca, cert = _load_cert(tls_dir / CA_CERT), _load_cert(tls_dir / CERT)
    try:
        key = serialization.load_pem_private_key((tls_dir / KEY).read_bytes(), password=None)
    except (ValueError, TypeError) as e:
        raise PkiError(f"{tls_dir / KEY}: unreadable private key ({e})") from None
    if key.public_key() != cert.public_key():
        raise PkiError(f"{tls_dir}: {KEY} is not the key of {CERT}")
    try:
        cert.verify_directly_issued_by(ca)
    except (InvalidSignature, ValueError, TypeError):
        raise PkiError(f"{tls_dir}: {CERT} is not signed by the swarm CA in {CA_CERT}") from None
    now = _now()
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        raise PkiError(f"{tls_dir / CERT}: not valid now (valid {cert.not_valid_before_utc:%Y-%m-%d} to "
                       f"{cert.not_valid_after_utc:%Y-%m-%d})")
    info = _info(cert)
    if info.common_name != common_name:
        raise PkiError(f"{tls_dir / CERT} is the certificate of {info.common_name!r}, not of {common_name!r}")
    return info


def create_swarm_pki(out: Path, swarm: str, robots: list[int], robot_dirs: dict[int, Path] | None = None,
                     monitor_dir: Path | None = None, ca_dir: Path | None = None) -> Path:
    """A CA for a new swarm and a certificate for each robot and the monitor; returns the CA folder.

    Defaults: ``<out>/ca/`` (the operator's, never copied to a robot), ``<out>/robot<i>/tls/``
    and ``<out>/monitor/``. Replaces a previous CA in that folder (a new swarm is a new CA)."""
    out = Path(out)
    ca = create_ca(ca_dir or out / "ca", swarm, overwrite=True)
    for i in robots:
        issue(ca, robot_name(i), (robot_dirs or {}).get(i, out / f"robot{i}" / "tls"))
    issue(ca, MONITOR_NAME, monitor_dir or out / "monitor")
    return ca
