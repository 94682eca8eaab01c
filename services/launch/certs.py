"""certs: a certificate authority and host certificates for Zenoh's mutual TLS.

``vistrack certs ca [--dir DIR] [--name NAME] [--days N] [--force]``
    creates ``DIR/ca.pem`` (the CA certificate, copied to every host) and ``DIR/ca.key`` (its
    private key: keep it on the machine where you issue certificates, never on a robot).
``vistrack certs issue NAME [--dir DIR] [--host HOST ...] [--days N] [--force]``
    creates ``DIR/NAME.pem`` and ``DIR/NAME.key``, signed by the CA in DIR. NAME is the
    certificate's common name: the name Zenoh's access control matches (``cert_common_names``
    in ``deploy/multi-host/router.json5``). ``--host`` adds the DNS names and IP addresses a
    host is reached at (a listening router needs them: clients check the name they connect
    to, ``verify_name_on_connect``). Every certificate serves both sides of a TLS link.
``vistrack certs show FILE ... [--ca CA.pem]``
    prints each certificate's common name, hosts, issuer and validity; with ``--ca``, checks
    that the CA signed it (exit 1 if not, or if it has expired).

Keys are ECDSA P-256 in PKCS#8 PEM, written with mode 0600; existing files are never
overwritten without ``--force``. Exit codes: 0 success, 1 a check failed, 2 bad input.
Needs the ``cryptography`` package; ``openssl`` can do the same (README, "Deploying across
machines").
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..usage import add_number, add_path, print_error

CA_CERT = "ca.pem"
CA_KEY = "ca.key"
DEFAULT_DIR = "certs"
CA_DAYS = 3650
HOST_DAYS = 825  # the longest validity browsers still accept; renew with `issue --force`
# a common name becomes a file name and an ACL entry: keep it to a safe, readable alphabet
_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
# a DNS name as certificates carry it (letters, digits, '-', dots; a leading '*.' wildcard)
_DNS_RE = re.compile(r"(\*\.)?([A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?\.?)+")


class CertError(Exception):
    """Bad input or a failed check, reported as one line; ``code`` is the exit code."""

    def __init__(self, message: str, code: int = 2) -> None:
        super().__init__(message)
        self.code = code


def _crypto() -> Any:
    """The ``cryptography`` modules this command uses, or a CertError saying how to get them."""
    try:
        from cryptography import x509
        from cryptography.exceptions import InvalidSignature
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError:
        raise CertError("needs the 'cryptography' package: pip install cryptography (or make "
                        "the files with openssl, see README 'Deploying across machines')",
                        code=1) from None
    return argparse.Namespace(x509=x509, hashes=hashes, serialization=serialization, ec=ec,
                              EKU=ExtendedKeyUsageOID, NameOID=NameOID,
                              InvalidSignature=InvalidSignature)


def validate_name(name: str) -> str:
    """A certificate common name: 1 to 64 of ``A-Z a-z 0-9 . _ -``, not starting with one of
    ``. _ -``; raises CertError otherwise."""
    if not _NAME_RE.fullmatch(name):
        raise CertError(f"name {name!r} is not allowed: 1 to 64 letters, digits, '.', '_' or "
                        "'-', starting with a letter or digit")
    return name


def _san_entries(c: Any, hosts: list[str]) -> list[Any]:
    out: list[Any] = []
    for host in hosts:
        try:
            out.append(c.x509.IPAddress(ipaddress.ip_address(host)))
            continue
        except ValueError:
            pass
        if not _DNS_RE.fullmatch(host) or len(host) > 253:
            raise CertError(f"--host {host!r} is neither an IP address nor a DNS name")
        out.append(c.x509.DNSName(host))
    return out


def _write_private(path: Path, data: bytes, force: bool) -> None:
    """Write ``data`` to ``path`` readable by its owner only (created 0600, never widened)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | (0 if force else os.O_EXCL)
    fd = os.open(path, flags, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)  # an existing file overwritten with --force keeps no wider mode


def _write_public(path: Path, data: bytes, force: bool) -> None:
    with open(path, "wb" if force else "xb") as f:
        f.write(data)


def _refuse_existing(paths: list[Path], force: bool) -> None:
    existing = [str(p) for p in paths if p.exists()]
    if existing and not force:
        raise CertError(f"{', '.join(existing)} already exist(s): use --force to replace")


def _new_key(c: Any) -> Any:
    return c.ec.generate_private_key(c.ec.SECP256R1())


def _key_pem(c: Any, key: Any) -> bytes:
    s = c.serialization
    return key.private_bytes(s.Encoding.PEM, s.PrivateFormat.PKCS8, s.NoEncryption())


def _now() -> dt.datetime:
    # backdated a little: a host whose clock is slightly behind must still accept it
    return dt.datetime.now(dt.timezone.utc) - dt.timedelta(minutes=5)


def make_ca(directory: Path, name: str = "vistrack CA", days: int = CA_DAYS,
            force: bool = False) -> tuple[Path, Path]:
    """Create a self-signed CA in ``directory``; return (certificate path, key path).

    Raises
    ------
    CertError
        If the files exist and not ``force``, or ``days`` is not positive.
    """
    c = _crypto()
    if days < 1:
        raise CertError(f"--days {days} must be >= 1")
    if not 1 <= len(name) <= 64:  # what X.509 allows in a common name
        raise CertError(f"--name {name!r} is {len(name)} characters long: a common name has "
                        "1 to 64")
    directory.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = directory / CA_CERT, directory / CA_KEY
    _refuse_existing([cert_path, key_path], force)
    key = _new_key(c)
    subject = c.x509.Name([c.x509.NameAttribute(c.NameOID.COMMON_NAME, name)])
    ski = c.x509.SubjectKeyIdentifier.from_public_key(key.public_key())
    cert = (c.x509.CertificateBuilder()
            .subject_name(subject).issuer_name(subject)
            .public_key(key.public_key())
            .serial_number(c.x509.random_serial_number())
            .not_valid_before(_now()).not_valid_after(_now() + dt.timedelta(days=days))
            .add_extension(c.x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(c.x509.KeyUsage(
                digital_signature=True, key_cert_sign=True, crl_sign=True,
                content_commitment=False, key_encipherment=False, data_encipherment=False,
                key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(ski, critical=False)
            .sign(key, c.hashes.SHA256()))
    _write_private(key_path, _key_pem(c, key), force)
    _write_public(cert_path, cert.public_bytes(c.serialization.Encoding.PEM), force)
    return cert_path, key_path


def _load_ca(c: Any, directory: Path) -> tuple[Any, Any]:
    cert_path, key_path = directory / CA_CERT, directory / CA_KEY
    if not cert_path.is_file() or not key_path.is_file():
        raise CertError(f"no CA in {directory}: run 'vistrack certs ca --dir {directory}' first "
                        f"(needs {CA_CERT} and {CA_KEY})")
    try:
        cert = c.x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = c.serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (ValueError, TypeError) as e:
        raise CertError(f"cannot read the CA in {directory}: {e}") from None
    return cert, key


def issue(directory: Path, name: str, hosts: list[str] | None = None, days: int = HOST_DAYS,
          force: bool = False) -> tuple[Path, Path]:
    """Issue ``directory/NAME.pem`` and ``NAME.key`` signed by the CA in ``directory``.

    The certificate's common name is ``name``; its subject alternative names are ``name``
    itself (when it is a valid DNS name) and ``hosts`` (DNS names or IP addresses). It may
    serve as TLS server and client (extended key usages serverAuth and clientAuth).

    Raises
    ------
    CertError
        Bad name, host or days; no CA in ``directory``; files exist and not ``force``.
    """
    c = _crypto()
    validate_name(name)
    if days < 1:
        raise CertError(f"--days {days} must be >= 1")
    ca_cert, ca_key = _load_ca(c, directory)
    names = list(dict.fromkeys([*([name] if _DNS_RE.fullmatch(name) else []), *(hosts or [])]))
    sans = _san_entries(c, names)
    cert_path, key_path = directory / f"{name}.pem", directory / f"{name}.key"
    if cert_path in (directory / CA_CERT,):
        raise CertError(f"name {name!r} would overwrite the CA certificate")
    _refuse_existing([cert_path, key_path], force)
    key = _new_key(c)
    not_after = min(_now() + dt.timedelta(days=days), ca_cert.not_valid_after_utc)
    aki = c.x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key())
    cert = (c.x509.CertificateBuilder()
            .subject_name(c.x509.Name([c.x509.NameAttribute(c.NameOID.COMMON_NAME, name)]))
            .issuer_name(ca_cert.subject)
            .public_key(key.public_key())
            .serial_number(c.x509.random_serial_number())
            .not_valid_before(_now()).not_valid_after(not_after)
            .add_extension(c.x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(c.x509.KeyUsage(
                digital_signature=True, key_encipherment=False, key_cert_sign=False,
                crl_sign=False, content_commitment=False, data_encipherment=False,
                key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(c.x509.ExtendedKeyUsage([c.EKU.SERVER_AUTH, c.EKU.CLIENT_AUTH]),
                           critical=False)
            .add_extension(c.x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(aki, critical=False)
            .add_extension(c.x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                           critical=False)
            .sign(ca_key, c.hashes.SHA256()))
    _write_private(key_path, _key_pem(c, key), force)
    _write_public(cert_path, cert.public_bytes(c.serialization.Encoding.PEM), force)
    return cert_path, key_path


@dataclass(frozen=True)
class CertInfo:
    """What ``show`` prints of a certificate."""

    path: str
    common_name: str
    hosts: tuple[str, ...]
    issuer: str
    not_before: dt.datetime
    not_after: dt.datetime
    is_ca: bool
    signed_by_ca: bool | None  # None: no CA given

    @property
    def expired(self) -> bool:
        return dt.datetime.now(dt.timezone.utc) > self.not_after


def inspect(path: Path, ca_path: Path | None = None) -> CertInfo:
    """Read a PEM certificate (and check its signature against ``ca_path``).

    Raises
    ------
    CertError
        If a file is missing or not a PEM certificate.
    """
    c = _crypto()

    def load(p: Path) -> Any:
        try:
            return c.x509.load_pem_x509_certificate(p.read_bytes())
        except OSError as e:
            raise CertError(f"{p}: {e.strerror}") from None
        except ValueError as e:
            raise CertError(f"{p}: not a PEM certificate ({e})") from None

    cert = load(path)
    cn = cert.subject.get_attributes_for_oid(c.NameOID.COMMON_NAME)
    issuer_cn = cert.issuer.get_attributes_for_oid(c.NameOID.COMMON_NAME)
    try:
        san = cert.extensions.get_extension_for_class(c.x509.SubjectAlternativeName).value
        hosts = tuple([*san.get_values_for_type(c.x509.DNSName),
                       *(str(ip) for ip in san.get_values_for_type(c.x509.IPAddress))])
    except c.x509.ExtensionNotFound:
        hosts = ()
    try:
        is_ca = cert.extensions.get_extension_for_class(c.x509.BasicConstraints).value.ca
    except c.x509.ExtensionNotFound:
        is_ca = False
    signed: bool | None = None
    if ca_path is not None:
        ca = load(ca_path)
        try:
            cert.verify_directly_issued_by(ca)
            signed = True
        except (ValueError, TypeError, c.InvalidSignature):  # other issuer, key type, signature
            signed = False
    return CertInfo(str(path), str(cn[0].value) if cn else "",
                    hosts, str(issuer_cn[0].value) if issuer_cn else cert.issuer.rfc4514_string(),
                    cert.not_valid_before_utc, cert.not_valid_after_utc, is_ca, signed)


# -- the command line ------------------------------------------------------------------------

def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", parser_class=type(parser))
    actions.required = True
    ca = actions.add_parser("ca", help="create the certificate authority (ca.pem, ca.key)")
    add_path(ca, "--dir", kind="folder", example=DEFAULT_DIR, default=DEFAULT_DIR,
             help=f"where to write (default {DEFAULT_DIR})")
    ca.add_argument("--name", default="vistrack CA", help="the CA's common name")
    add_number(ca, "--days", lo=1, hi=36500, integer=True, default=CA_DAYS, metavar="N",
               help=f"validity in days, %(allowed)s (default {CA_DAYS})")
    ca.add_argument("--force", action="store_true", help="replace existing files")
    iss = actions.add_parser("issue", help="issue NAME.pem and NAME.key signed by the CA")
    iss.add_argument("name", metavar="NAME",
                     help="common name, matched by the access control (e.g. vistrack-robot)")
    add_path(iss, "--dir", kind="folder", example=DEFAULT_DIR, default=DEFAULT_DIR,
             help=f"where the CA is and the files go (default {DEFAULT_DIR})")
    iss.add_argument("--host", action="append", default=[], metavar="HOST",
                     help="a DNS name or IP address the host is reached at (repeatable)")
    add_number(iss, "--days", lo=1, hi=36500, integer=True, default=HOST_DAYS, metavar="N",
               help=f"validity in days, %(allowed)s (default {HOST_DAYS})")
    iss.add_argument("--force", action="store_true", help="replace existing files")
    show = actions.add_parser("show", help="print certificates; check them against a CA")
    add_path(show, "files", example="certs/robot.pem", nargs="+", metavar="FILE.pem")
    add_path(show, "--ca", example="certs/ca.pem", metavar="CA.pem",
             help="check each certificate was signed by it")


def main(args: argparse.Namespace) -> int:
    try:
        if args.action == "ca":
            cert, key = make_ca(Path(args.dir), args.name, args.days, args.force)
            print(f"wrote {cert} (copy to every host) and {key} (keep it private, off the "
                  "robots)")
        elif args.action == "issue":
            cert, key = issue(Path(args.dir), args.name, args.host, args.days, args.force)
            print(f"wrote {cert} and {key} (common name {args.name})")
        else:
            return _show(args)
    except CertError as e:
        print_error("certs", e)
        return e.code
    except OSError as e:
        print_error("certs", f"{e.filename}: {e.strerror}")
        return 2
    return 0


def _show(args: argparse.Namespace) -> int:
    code = 0
    for name in args.files:
        info = inspect(Path(name), Path(args.ca) if args.ca else None)
        checks = []
        if info.expired:
            checks.append("EXPIRED")
            code = 1
        if info.signed_by_ca is not None:
            checks.append("signed by the CA" if info.signed_by_ca else "NOT signed by the CA")
            code = code or (0 if info.signed_by_ca else 1)
        print(f"{info.path}: CN={info.common_name}{' (CA)' if info.is_ca else ''} "
              f"hosts=[{', '.join(info.hosts)}] issuer={info.issuer} "
              f"valid {info.not_before:%Y-%m-%d} to {info.not_after:%Y-%m-%d}"
              + (f" ({', '.join(checks)})" if checks else ""))
    return code
