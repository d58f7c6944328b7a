"""Issue 43, the findings left open after attack round 20: certificate chains that pass every
field check yet fail path validation in clients (Y7) are refused at start-up by a TLS
handshake in memory through OpenSSL's verifier; a trusted CA-file certificate that may not
sign (Y6) is named by both clients; the DER rule of certificate files reads the same in the
Python reader and the C++ client (strings in constructed form, extension values, unique IDs)."""

from __future__ import annotations

import os
from datetime import datetime, timedelta, timezone

import pytest

from slamreloc.service.server import handshake_problem, read_tls_pair
from tests.test_round18 import der, make_certificate, pem

pytest.importorskip("cryptography")


def _key_pem(key) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _v1_certificate(subject: str, issuer):
    """(certificate, key): a version 1 certificate (no extensions) signed by `issuer`."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.now(timezone.utc)
    builder = (x509.CertificateBuilder()
               .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
               .issuer_name(issuer[0].subject).public_key(key.public_key()).serial_number(7)
               .not_valid_before(now - timedelta(days=1))
               .not_valid_after(now + timedelta(days=1)))
    builder._version = x509.Version.v1  # cryptography writes version 3 only; the test needs 1
    return builder.sign(issuer[1], hashes.SHA256()), key


def _chains():
    """(name, leaf key, chain PEM, words of the refusal or None) for chains whose every
    certificate passes the field checks."""
    from cryptography import x509
    from cryptography.x509.oid import ExtendedKeyUsageOID

    root = make_certificate("root", ca=True, days=(-30, 30))
    out = []
    intermediate = make_certificate("int", issuer=root, ca=True, days=(-30, 30))
    leaf, key = make_certificate("localhost", issuer=intermediate)
    out.append(("valid", key, [leaf, intermediate[0], root[0]], None))
    client_only = make_certificate("int", issuer=root, ca=True, days=(-30, 30), extensions=[
        (x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CLIENT_AUTH]), False)])
    leaf, key = make_certificate("localhost", issuer=client_only)
    out.append(("clientAuth-only intermediate", key, [leaf, client_only[0], root[0]],
                "certificate purpose"))
    zero = make_certificate("root0", days=(-30, 30), extensions=[
        (x509.BasicConstraints(ca=True, path_length=0), True)])
    below = make_certificate("int", issuer=zero, ca=True, days=(-30, 30))
    leaf, key = make_certificate("localhost", issuer=below)
    out.append(("path length exceeded", key, [leaf, below[0], zero[0]], "path length"))
    constrained = make_certificate("rootnc", ca=True, days=(-30, 30), extensions=[
        (x509.NameConstraints(permitted_subtrees=[x509.DNSName("example.org")],
                              excluded_subtrees=None), True)])
    leaf, key = make_certificate("localhost", issuer=constrained, extensions=[
        (x509.SubjectAlternativeName([x509.DNSName("localhost")]), False)])
    out.append(("outside the name constraints", key, [leaf, constrained[0]], "subtree"))
    old = _v1_certificate("int", root)
    leaf, key = make_certificate("localhost", issuer=old)
    out.append(("version 1 intermediate", key, [leaf, old[0], root[0]], "CA certificate"))
    alone, key = make_certificate("localhost")  # self-signed, no basicConstraints
    out.append(("self-signed, no basicConstraints", key, [alone], None))
    return out


@pytest.mark.parametrize("case", range(6))
def test_a_chain_clients_cannot_validate_is_refused_at_start_up(case, tmp_path):
    """Y7: a version 1 intermediate, an intermediate for clientAuth only, a path length or a
    name constraint broken: each certificate passed the field checks and the server started;
    every client's handshake then failed. A valid chain and a lone self-signed certificate
    (the common test set-up) still start."""
    name, key, chain, words = _chains()[case]
    cert = b"".join(pem(der(one)) for one in chain)
    problem = handshake_problem(_key_pem(key), cert)
    if words is None:
        assert problem is None, (name, problem)
        return
    assert problem is not None and words in problem, (name, problem)
    (tmp_path / "c.pem").write_bytes(cert)
    (tmp_path / "k.pem").write_bytes(_key_pem(key))
    with pytest.raises(Exception, match=r"c\.pem: `tls_cert` cannot serve TLS: clients refuse"):
        read_tls_pair(tmp_path / "c.pem", tmp_path / "k.pem")


def crafted_certificates() -> dict[str, tuple[bytes, str | None]]:
    """name -> (certificate DER, words of the refusal, None where it is taken): the DER corner
    cases left open after round 20, where one client refused what the other took."""
    from cryptography import x509
    from cryptography.x509.oid import ObjectIdentifier

    from tests.test_round19 import parse_der, walk, write_der

    unknown = x509.UnrecognizedExtension(ObjectIdentifier("1.2.3.4.5.6.7"), b"\x02\x01\x05")
    base = der(make_certificate("c", extensions=[(unknown, False)])[0])
    out: dict[str, tuple[bytes, str | None]] = {"plain": (base, None)}

    def edited(change) -> bytes:
        tree = parse_der(base)
        change(tree[0][1][0][1])  # the signed part's elements
        return write_der(tree)

    def constructed_name(tbs):  # the subject's CN as a constructed UTF8String (BER)
        for holder, i in walk(tbs):
            tag, body = holder[i]
            if tag == 0x0C and body == b"c":
                holder[i] = (0x2C, [(0x0C, b"c")])
                return
    out["a constructed string in a name"] = (edited(constructed_name),
                                             "a string written in constructed form")

    def unique_id(padding: int):
        def change(tbs):
            tbs.insert(7, (0x81, bytes([3, 0xF0 | padding])))  # after subjectPublicKeyInfo
        return change
    out["an issuer unique ID, padding 0"] = (edited(unique_id(0)), None)
    out["an issuer unique ID, padding set"] = (edited(unique_id(1)),
                                               "a unique ID whose unused bits are not 0")

    def extension_value(value: bytes):
        def change(tbs):
            for holder, i in walk(tbs):
                tag, body = holder[i]
                if tag == 0x04 and body == b"\x02\x01\x05":
                    holder[i] = (tag, value)
                    return
        return change
    out["an extension holding a long length"] = (
        edited(extension_value(b"\x02\x81\x01\x05")), "a length not in its shortest form")
    out["an extension holding a padded integer"] = (
        edited(extension_value(b"\x02\x02\x00\x05")), "an INTEGER not in its shortest form")
    out["an extension holding no DER"] = (edited(extension_value(b"\x02\x05\x05")),
                                          "an element cut short")
    return out


def test_the_der_rule_reads_inside_names_unique_ids_and_extension_values():
    """Round 20's open DER cases: a constructed string in a name (the C++ client refused it,
    Python took it), a unique ID with padding bits set and BER inside an extension's value
    (Python refused them, the C++ client took them). Both now read by one rule;
    tests/test_cpp_client.py runs the same certificates through the C++ client."""
    from slamreloc.io.pem import certificates_der

    for name, (data, words) in crafted_certificates().items():
        if words is None:
            assert certificates_der(pem(data)) == [data], name
            continue
        with pytest.raises(ValueError, match="not in strict DER") as caught:
            certificates_der(pem(data))
        assert words in str(caught.value), (name, caught.value)


def test_a_trusted_certificate_that_can_anchor_nothing_is_refused_by_the_client(tmp_path):
    """Y6: a CA file holding a certificate that is neither a CA nor self-signed: no verifier
    anchors a chain in it (the Python client's BoringSSL took one as the issuer of the
    server's certificate, the C++ client's OpenSSL refused it). Both clients now refuse it
    before connecting; a CA signed by another, and self-signed certificates, are taken."""
    from cryptography import x509

    from slamreloc.client import Client
    from slamreloc.errors import InputError
    from slamreloc.io.pem import trusted_certificates_problem

    root = make_certificate("root", ca=True)
    leaf = make_certificate("leaf", issuer=root)[0]
    no_sign = make_certificate("ca", issuer=root, ca=True,
                               extensions=[(x509.KeyUsage(True, *[False] * 8), True)])[0]
    taken = [root[0], make_certificate("int", issuer=root, ca=True)[0], make_certificate()[0]]
    for one in taken:
        assert trusted_certificates_problem(pem(der(one))) is None
    for one, number in ((leaf, 2), (no_sign, 2)):
        data = pem(der(root[0])) + pem(der(one))
        assert f"certificate {number} (CN=" in trusted_certificates_problem(data)
        (tmp_path / "ca.pem").write_bytes(data)
        with pytest.raises(InputError, match=r"ca\.pem: `tls_ca` cannot be trusted: certif"
                                             r"icate 2 \(CN=.*\) is neither a CA nor self-s"):
            Client("127.0.0.1:1", tls_ca=tmp_path / "ca.pem")


def rsa_certificate(subject: str, bits: int = 2048, issuer=None, ca: bool = True):
    """(certificate, key): an RSA certificate signed (SHA-256) by `issuer` or itself."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import rsa
    from cryptography.x509.oid import NameOID

    key = rsa.generate_private_key(65537, bits)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)])
    signer_name, signer_key = (name, key) if issuer is None else (issuer[0].subject, issuer[1])
    now = datetime.now(timezone.utc)
    builder = (x509.CertificateBuilder().subject_name(name).issuer_name(signer_name)
               .public_key(key.public_key()).serial_number(5)
               .not_valid_before(now - timedelta(days=1)).not_valid_after(now + timedelta(days=1)))
    if ca:
        builder = builder.add_extension(x509.BasicConstraints(ca=True, path_length=None), True)
    return builder.sign(signer_key, hashes.SHA256()), key


SHA256_RSA = bytes.fromhex("06092a864886f70d01010b")  # the OID sha256WithRSAEncryption


def sha1_signed(certificate_der: bytes) -> bytes:
    """The RSA-signed certificate with its signature algorithm named sha1WithRSAEncryption
    (both places; the signature no longer verifies, which no CA-file reader checks):
    cryptography signs no SHA-1."""
    assert certificate_der.count(SHA256_RSA) == 2
    return certificate_der.replace(SHA256_RSA, SHA256_RSA[:-1] + b"\x05")


def weak_trusted_certificates() -> dict[str, tuple[bytes, str | None]]:
    """name -> (PEM CA file, words of the refusal or None): round 21's Z4 anchors."""
    root = rsa_certificate("root")
    intermediate = rsa_certificate("int", issuer=root)[0]
    return {
        "RSA-1024 root": (pem(der(rsa_certificate("r1024", 1024)[0])),
                          "80 security bits, under the 112"),
        "SHA-1 intermediate": (pem(der(root[0])) + pem(sha1_signed(der(intermediate))),
                               "is signed with SHA1"),
        "SHA-1 self-signed root": (pem(sha1_signed(der(root[0]))), None),
        "RSA-2048 root and intermediate": (pem(der(root[0])) + pem(der(intermediate)), None),
    }


def test_trusted_certificates_below_openssl_level_2_are_refused():
    """Z4 (round 21): a CA file with an RSA-1024 root, or an intermediate signed with SHA-1,
    was taken by both clients; the Python client (BoringSSL) then connected and the C++
    client (OpenSSL) refused every chain through it. Both refuse such a file now (the C++
    side: tests/test_cpp_client.py); a self-signed root's own SHA-1 signature is never
    checked by OpenSSL, so it stays taken."""
    from slamreloc.io.pem import trusted_certificates_problem

    for name, (data, words) in weak_trusted_certificates().items():
        problem = trusted_certificates_problem(data)
        assert (problem is None) if words is None else (words in problem), (name, problem)


def test_the_start_up_handshake_refuses_what_openssl_clients_refuse(tmp_path):
    """Z3, Z4 (round 21): the start-up handshake ran at OpenSSL's security level 0, so a chain
    signed with MD5 or SHA-1 or through an RSA-1024 CA started the server; every client (MD5)
    or the C++ client (the others) then failed. Z2: it handed the user's key file to OpenSSL,
    which asked for a pass phrase on the terminal; it now hands OpenSSL the key as written
    by `cryptography`, and key files follow the certificate files' form."""
    from slamreloc.errors import InputError
    from slamreloc.io.pem import pem_problem

    weak_ca = rsa_certificate("ca1024", 1024)
    leaf, key = make_certificate("localhost", issuer=weak_ca)
    assert "CA certificate key too weak" in handshake_problem(
        _key_pem(key), pem(der(leaf)) + pem(der(weak_ca[0])))
    ca = rsa_certificate("ca")
    leaf, key = make_certificate("localhost", issuer=ca)
    assert handshake_problem(_key_pem(key), pem(der(leaf)) + pem(der(ca[0]))) is None
    # a key file whose first marker follows other text, then an encrypted key: refused by
    # the form rule before anything reads it (it once prompted for a pass phrase)
    from cryptography.hazmat.primitives import serialization

    encrypted = key.private_bytes(serialization.Encoding.PEM,
                                  serialization.PrivateFormat.PKCS8,
                                  serialization.BestAvailableEncryption(b"secret"))
    forms = {"marker after text": b"x" + _key_pem(key) + encrypted,
             "nul line": b"\0\n" + _key_pem(key),
             "header": _key_pem(key).replace(b"KEY-----\n", b"KEY-----\nComment: hi\n\n", 1),
             "cr only": _key_pem(key).replace(b"\n", b"\r"),
             "indented": b"".join(b"  " + line for line in _key_pem(key).splitlines(True))}
    (tmp_path / "c.pem").write_bytes(pem(der(leaf)) + pem(der(ca[0])))
    for name, data in forms.items():
        assert pem_problem(data, "private key") is not None, name
        (tmp_path / "k.pem").write_bytes(data)
        with pytest.raises(InputError, match=r"k\.pem: `tls_key` is not a PEM private key"):
            read_tls_pair(tmp_path / "c.pem", tmp_path / "k.pem")


def test_a_token_keeps_the_unicode_blanks_around_it_and_is_refused(tmp_path, monkeypatch):
    """V1 (round 22): a token with a no-break space (or U+2028, U+0085, \\x1c) at its ends was
    trimmed and taken by the server and the Python client (`str.strip` drops all Unicode
    whitespace) while the C++ client refused it. ASCII blanks are dropped by all three; any
    other character stays and `token_problem` refuses it."""
    from slamreloc.client import Client
    from slamreloc.errors import InputError
    from slamreloc.service.server import read_token

    good = "a-token-of-24-characters"
    (tmp_path / "t").write_text(f" \t{good}\r\n")
    assert read_token(tmp_path / "t") == good
    for blank in ("\u00a0", "\u2028", "\u0085", "\x1c"):
        (tmp_path / "t").write_text(f"{good}{blank}\n", encoding="utf-8")
        with pytest.raises(InputError, match="must be printable ASCII"):
            read_token(tmp_path / "t")
        monkeypatch.setenv("SLAMRELOC_TOKEN", blank + good)
        with pytest.raises(InputError, match="must be printable ASCII"):
            read_token(None)
        with pytest.raises(InputError, match="must be printable ASCII"):
            Client("127.0.0.1:1", token=good + blank)


def test_stopping_cancels_a_load_inside_a_file_s_checksum(tmp_path):
    """V2 (round 22): SIGTERM during a reload of a map whose database.npz was a 15 GiB
    sparse file waited until the whole file was hashed (30-72 s): the cancel was checked
    between files only. It is now checked every MiB of a checksum read."""
    import threading
    import time

    from slamreloc.io.fileio import CANCEL_READS
    from slamreloc.service.maps import LoadCancelled, ServedMap
    from tests.test_fuzz_inputs import _tiny_map

    root = _tiny_map(tmp_path / "map")
    os.truncate(root / "database.npz", 8 << 30)  # sparse: no disk used, seconds to hash
    stop = threading.Event()
    token = CANCEL_READS.set(stop)
    try:
        threading.Timer(0.5, stop.set).start()
        t0 = time.perf_counter()
        with pytest.raises(LoadCancelled, match="load cancelled"):
            ServedMap.load("m", root)
        assert time.perf_counter() - t0 < 5.0  # not the whole file
    finally:
        CANCEL_READS.reset(token)
