"""``xm certs``: a certificate authority and one certificate per host of a deployment.

The routers of a multi-host deployment link over TLS with client certificates on both sides
(mutual TLS): a router accepts only peers whose certificate the deployment's CA signed, and the
certificate's common name (the host's name in the deployment) is what the access-control rules
name (deploy/hosts.py). Files, in ``--out`` (default ``certs/`` beside the deployment file):
``ca.pem`` (give it to every host), ``ca.key`` (keep it off the hosts), ``<host>.pem`` and
``<host>.key`` (that host only). Keys are ECDSA P-256; certificates are valid for ``--days``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import sys
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from deploy.hosts import HostError, load_hosts
from shared.config import ConfigError, load_deployment


def _write_key(key: ec.EllipticCurvePrivateKey, path: Path) -> None:
    path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))
    path.chmod(0o600)


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "crossmodal workcell"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def make_ca(out: Path, days: int = 825,
            now: dt.datetime | None = None) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """A self-signed CA in ``out/ca.pem`` and ``out/ca.key``."""
    now = now or dt.datetime.now(dt.UTC)
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (x509.CertificateBuilder().subject_name(_name("crossmodal CA")).issuer_name(_name("crossmodal CA"))
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    out.mkdir(parents=True, exist_ok=True)
    (out / "ca.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(key, out / "ca.key")
    return cert, key


def make_host_cert(out: Path, host: str, addresses: list[str], ca: x509.Certificate,
                   ca_key: ec.EllipticCurvePrivateKey, days: int = 825, now: dt.datetime | None = None) -> Path:
    """``out/<host>.pem`` and ``.key``: common name ``host``, the addresses as subject names, usable
    as server and client (a router both listens and connects)."""
    now = now or dt.datetime.now(dt.UTC)
    key = ec.generate_private_key(ec.SECP256R1())
    names: list[x509.GeneralName] = [x509.DNSName(host)]
    for a in addresses:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(a)))
        except ValueError:
            names.append(x509.DNSName(a))
    cert = (x509.CertificateBuilder().subject_name(_name(host)).issuer_name(ca.subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.SubjectAlternativeName(names), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))
    (out / f"{host}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(key, out / f"{host}.key")
    return out / f"{host}.pem"


def check_cert(path: Path, ca_path: Path, now: dt.datetime | None = None) -> str | None:
    """Why the certificate at ``path`` cannot be used with the CA at ``ca_path`` (None: it can)."""
    now = now or dt.datetime.now(dt.UTC)
    try:
        cert = x509.load_pem_x509_certificate(path.read_bytes())
        ca = x509.load_pem_x509_certificate(ca_path.read_bytes())
    except (OSError, ValueError) as exc:
        return f"{path}: cannot be read as a PEM certificate ({exc})"
    if cert.not_valid_after_utc < now:
        return f"{path}: expired on {cert.not_valid_after_utc:%Y-%m-%d} (run `xm certs` again)"
    if cert.not_valid_before_utc > now:
        return f"{path}: not valid before {cert.not_valid_before_utc:%Y-%m-%d %H:%M} (check the host's clock)"
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature) as exc:
        return f"{path}: not signed by the CA in {ca_path} ({type(exc).__name__}); was it made for another deployment?"
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xm certs", description=__doc__.split("\n\n")[0])
    parser.add_argument("deployment", help="a deployment file with [hosts.*] tables")
    parser.add_argument("--out", type=Path, help="directory (default: the deployment's [tls] dir)")
    parser.add_argument("--days", type=int, default=825, help="validity in days (default %(default)s)")
    args = parser.parse_args(argv)
    try:
        deployment = load_deployment(args.deployment)
        hosts = load_hosts(deployment)
    except (ConfigError, HostError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not hosts.hosts:
        print(f"error: {args.deployment} has no [hosts.*] tables: one host needs no certificates", file=sys.stderr)
        return 2
    out = args.out or hosts.tls_dir
    ca, ca_key = make_ca(out, args.days)
    for host in hosts.hosts.values():
        make_host_cert(out, host.name, [host.address], ca, ca_key, args.days)
        print(f"{out / host.name}.pem  ({host.name}, {host.address})")
    print(f"{out / 'ca.pem'}: copy it and each host's .pem/.key to that host; keep {out / 'ca.key'} elsewhere")
    return 0
