"""``vistrack certs``: the CA and host certificates Zenoh's mutual TLS is configured with.

Checked with the ``cryptography`` package's own verification and, where installed, with
``openssl verify`` as an independent reference. That Zenoh accepts them (and refuses others) is
tested in tests/integration/test_multihost.py.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import shutil
import stat
import subprocess

import pytest

from vistrack.services import cli
from vistrack.services.launch.certs import CertError, inspect, issue, make_ca

x509 = pytest.importorskip("cryptography.x509", reason="vistrack certs needs cryptography")
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID  # noqa: E402


def load(path):
    return x509.load_pem_x509_certificate(path.read_bytes())


@pytest.fixture
def ca_dir(tmp_path):
    make_ca(tmp_path)
    return tmp_path


def test_ca_is_a_self_signed_ca_with_a_private_key(ca_dir):
    ca = load(ca_dir / "ca.pem")
    assert ca.subject == ca.issuer
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    ca.verify_directly_issued_by(ca)
    assert stat.S_IMODE((ca_dir / "ca.key").stat().st_mode) == 0o600
    assert ca.not_valid_after_utc - ca.not_valid_before_utc > dt.timedelta(days=3000)


def test_host_certificate_names_hosts_and_both_tls_roles(ca_dir):
    cert_path, key_path = issue(ca_dir, "vistrack-router", ["router.lan", "10.77.0.1", "::1"])
    cert = load(cert_path)
    cert.verify_directly_issued_by(load(ca_dir / "ca.pem"))
    cn = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value
    assert cn == "vistrack-router"  # what the access control's cert_common_names matches
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["vistrack-router", "router.lan"]
    assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("10.77.0.1"),
                                                       ipaddress.ip_address("::1")]
    eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert set(eku) == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
    assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert stat.S_IMODE(key_path.stat().st_mode) == 0o600
    assert "PRIVATE KEY" in key_path.read_text()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")
def test_openssl_verifies_the_chain_for_both_purposes(ca_dir):
    cert_path, _ = issue(ca_dir, "vistrack-robot")
    for purpose in ("sslserver", "sslclient"):
        proc = subprocess.run(["openssl", "verify", "-purpose", purpose, "-CAfile",
                               str(ca_dir / "ca.pem"), str(cert_path)],
                              capture_output=True, text=True)
        assert proc.returncode == 0 and ": OK" in proc.stdout, proc.stdout + proc.stderr


def test_existing_files_are_kept_unless_forced(ca_dir):
    cert_path, _ = issue(ca_dir, "vistrack-base")
    before = cert_path.read_bytes()
    with pytest.raises(CertError, match="already exist"):
        issue(ca_dir, "vistrack-base")
    with pytest.raises(CertError, match="already exist"):
        make_ca(ca_dir)
    assert cert_path.read_bytes() == before
    issue(ca_dir, "vistrack-base", force=True)
    assert cert_path.read_bytes() != before


@pytest.mark.parametrize("name", ["", "-dash", "has space", "a/b", "x" * 65])
def test_bad_names_are_refused(ca_dir, name):
    with pytest.raises(CertError, match="not allowed"):
        issue(ca_dir, name)


def test_bad_host_and_missing_ca_are_refused(tmp_path, ca_dir):
    with pytest.raises(CertError, match="neither an IP address nor a DNS name"):
        issue(ca_dir, "vistrack-robot", ["not a host"])
    with pytest.raises(CertError, match="no CA in"):
        issue(tmp_path / "empty", "vistrack-robot")


def test_validity_never_outlives_the_ca(tmp_path):
    make_ca(tmp_path, days=10)
    cert = load(issue(tmp_path, "vistrack-robot", days=825)[0])
    assert cert.not_valid_after_utc <= load(tmp_path / "ca.pem").not_valid_after_utc


def test_inspect_tells_our_certificates_from_another_cas(tmp_path, ca_dir):
    ours = issue(ca_dir, "vistrack-robot")[0]
    make_ca(tmp_path / "other", "vistrack CA")  # same name, another key
    theirs = issue(tmp_path / "other", "vistrack-robot")[0]
    assert inspect(ours, ca_dir / "ca.pem").signed_by_ca is True
    assert inspect(theirs, ca_dir / "ca.pem").signed_by_ca is False
    info = inspect(ours)
    assert (info.common_name, info.is_ca, info.expired) == ("vistrack-robot", False, False)


def test_command_line(tmp_path, capsys):
    d = str(tmp_path)
    assert cli.main(["certs", "ca", "--dir", d]) == 0
    assert cli.main(["certs", "issue", "vistrack-robot", "--dir", d, "--host", "10.0.0.2"]) == 0
    assert "common name vistrack-robot" in capsys.readouterr().out
    assert cli.main(["certs", "issue", "vistrack-robot", "--dir", d]) == 2
    assert "already exist" in capsys.readouterr().err
    assert cli.main(["certs", "show", f"{d}/vistrack-robot.pem", "--ca", f"{d}/ca.pem"]) == 0
    out = capsys.readouterr().out
    assert "CN=vistrack-robot" in out and "10.0.0.2" in out and "signed by the CA" in out
    make_ca(tmp_path / "other")
    assert cli.main(["certs", "show", f"{d}/vistrack-robot.pem",
                     "--ca", f"{tmp_path}/other/ca.pem"]) == 1
    assert "NOT signed by the CA" in capsys.readouterr().out
    assert cli.main(["certs", "show", f"{d}/missing.pem"]) == 2
    capsys.readouterr()
    assert cli.main(["certs", "issue", "x", "--days", "0"]) == 2
    assert capsys.readouterr().err == ("vistrack certs: error: --days 0 is out of range: "
                                       "allowed 1..36500\n")
    assert cli.main(["certs", "ca", "--dir", str(tmp_path / "long"), "--name", "x" * 65]) == 2
    assert capsys.readouterr().err == ("vistrack certs: error: --name '" + "x" * 65 + "' is 65 "
                                       "characters long: a common name has 1 to 64\n")
