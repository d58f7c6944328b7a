"""Issue 43, attack round 17: TLS pairs `serve` started with although no client could use them
(a key usage without signatures, a client-only extended key usage) or that gRPC refused under
a message blaming the port (an RSA-PSS key, an ECDSA curve given by explicit parameters)."""

from __future__ import annotations

import shutil
import subprocess
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest

from slamreloc.service.server import certificate_problem
from tests.fuzzing import run_cli
from tests.test_fuzz_inputs import _tiny_map

pytest.importorskip("cryptography")


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round17") / "map")


def _certificate(key, *extensions) -> bytes:
    """A self-signed certificate of `key` for localhost, valid now, with `extensions`
    ((extension, critical) pairs)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.x509.oid import NameOID

    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "localhost")])
    now = datetime.now(timezone.utc)
    builder = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
               .public_key(key.public_key()).serial_number(1)
               .not_valid_before(now - timedelta(days=1))
               .not_valid_after(now + timedelta(days=1)))
    for extension, critical in extensions:
        builder = builder.add_extension(extension, critical)
    return builder.sign(key, hashes.SHA256()).public_bytes(serialization.Encoding.PEM)


def _usage(**allowed):
    from cryptography import x509

    flags = dict.fromkeys(("digital_signature", "content_commitment", "key_encipherment",
                           "data_encipherment", "key_agreement", "key_cert_sign", "crl_sign",
                           "encipher_only", "decipher_only"), False)
    return x509.KeyUsage(**{**flags, **allowed}), True


def _purposes(*oids):
    from cryptography import x509

    return x509.ExtendedKeyUsage(list(oids)), False


def test_a_certificate_whose_usages_no_tls_server_may_use_is_refused():
    """T1: keyUsage keyCertSign only (the server's log: KEY_USAGE_BIT_INCORRECT on every
    handshake) and extendedKeyUsage clientAuth only (the C++ client's OpenSSL refuses it)
    started the server. Each is refused, saying why; the usages a server has are taken."""
    from cryptography.hazmat.primitives.asymmetric import ec, rsa
    from cryptography.x509.oid import ExtendedKeyUsageOID as EKU

    key = ec.generate_private_key(ec.SECP256R1())
    assert "does not allow digitalSignature" in certificate_problem(
        _certificate(key, _usage(key_cert_sign=True)))
    rsa_key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    assert "does not allow digitalSignature" in certificate_problem(  # RSA key exchange: none
        _certificate(rsa_key, _usage(key_encipherment=True)))
    assert "allows only clientAuth, not serverAuth" in certificate_problem(
        _certificate(key, _purposes(EKU.CLIENT_AUTH)))
    for fine in ((), (_usage(digital_signature=True),),
                 (_usage(digital_signature=True, key_encipherment=True),
                  _purposes(EKU.SERVER_AUTH, EKU.CLIENT_AUTH)),
                 (_purposes(EKU.ANY_EXTENDED_KEY_USAGE),)):
        assert certificate_problem(_certificate(key, *fine)) is None, fine


def _openssl(tmp_path: Path, *args: str) -> None:
    subprocess.run(["openssl", *args], cwd=tmp_path, check=True, capture_output=True)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
@pytest.mark.parametrize("kind", ["rsa-pss", "explicit-curve"])
def test_keys_grpc_refuses_are_refused_naming_the_certificate(tmp_path, tiny_map, kind):
    """T2: an RSA-PSS key, or an ECDSA key whose curve is given by explicit parameters (read
    by `cryptography` as plain RSA and as the named P-256), reached gRPC, which refused the
    pair: the start failed with three lines of gRPC's log and `--port 0 / --host: cannot
    listen`, the TLS pair last, as a maybe. They are refused before gRPC, in one line naming
    `--tls-cert` and the key."""
    if kind == "rsa-pss":
        _openssl(tmp_path, "genpkey", "-algorithm", "RSA-PSS", "-pkeyopt",
                 "rsa_keygen_bits:2048", "-out", "key.pem")
    else:
        _openssl(tmp_path, "ecparam", "-name", "prime256v1", "-param_enc", "explicit",
                 "-genkey", "-noout", "-out", "key.pem")
    _openssl(tmp_path, "req", "-new", "-x509", "-key", "key.pem", "-out", "cert.pem",
             "-days", "1", "-subj", "/CN=localhost")
    code, err = run_cli(["serve", str(tiny_map), "--port", "0", "--watch", "0", "--tls-cert",
                         str(tmp_path / "cert.pem"), "--tls-key", str(tmp_path / "key.pem")],
                        hang_s=60)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    want = "RSA-PSS only" if kind == "rsa-pss" else "explicit parameters"
    assert lines[0].startswith(f"error: {tmp_path / 'cert.pem'}: --tls-cert cannot serve TLS")
    assert want in lines[0] and "cannot listen" not in lines[0], lines[0]
