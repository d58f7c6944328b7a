"""PEM files for TLS (`serve --tls-cert/--tls-key`, a client's trusted CA): one reader and
one rule for the server, the Python client and (mirrored) the C++ client."""

from __future__ import annotations

import warnings
from pathlib import Path

from slamreloc.errors import InputError

MAX_PEM_BYTES = 1 << 20  # a certificate chain or key file


def read_pem(path: Path, what: str, setting: str) -> bytes:
    """The bytes of the PEM `what` ("private key" or "certificate") at `path`; InputError
    naming the file and its `setting` when it is no regular file, over MAX_PEM_BYTES, or not
    such a PEM (`pem_problem`)."""
    from slamreloc.io.fileio import read_bytes

    return check_pem(read_bytes(path, f"TLS {what} (`{setting}`)", MAX_PEM_BYTES), what,
                     setting, path)


def check_pem(data: bytes, what: str, setting: str, path: Path | None = None) -> bytes:
    """`data` if it is a PEM `what` (`pem_problem`); else InputError naming its `setting`
    (and the file it came from, where it came from one)."""
    where = f"{path}: " if path is not None else ""
    if len(data) > MAX_PEM_BYTES:  # given as bytes (the Python client's tls_ca=...)
        raise InputError(f"{where}`{setting}` is {len(data)} bytes, over the {MAX_PEM_BYTES} a "
                         f"PEM {what} may hold")
    problem = pem_problem(data, what)
    if problem:
        raise InputError(f"{where}`{setting}` is not a PEM {what} ({problem})")
    return data


def pem_problem(data: bytes, what: str) -> str | None:
    """Why `data` is not a PEM `what` ("private key" or "certificate"), or None."""
    if data.startswith(b"\xef\xbb\xbf"):  # Python's parsers skip it, gRPC's TLS does not
        return ("it starts with a UTF-8 byte-order mark, which gRPC's TLS does not read: save "
                "it without")
    if what != "private key":
        try:
            certificates_der(data)
        except ValueError as err:
            return str(err)
        return None
    try:  # the certificate files' form: gRPC reads both with one PEM reader
        blocks = pem_blocks(data)
    except ValueError as err:
        return str(err)
    if not any(label.endswith("PRIVATE KEY") for label, _, _ in blocks):
        return "no 'PRIVATE KEY' block"
    try:
        from cryptography.hazmat.primitives.serialization import load_pem_private_key
    except ImportError:
        return None
    try:
        load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as err:  # cryptography's parse errors
        return " ".join(str(err).split())[:200] or type(err).__name__
    except Exception as err:  # noqa: BLE001 - an unsupported algorithm, a Rust-side error
        return f"{type(err).__name__}: {' '.join(str(err).split())[:200]}"
    return None


# The labels of a certificate's PEM block (OpenSSL reads both as one); a TRUSTED CERTIFICATE
# (OpenSSL's certificate with trust settings) is refused by name: TLS here does not read it.
CERTIFICATE_LABELS = ("CERTIFICATE", "X509 CERTIFICATE")
MAX_PEM_LINE = 76  # characters of a line inside a block (RFC 7468 writes 64, MIME 76)
_BASE64 = frozenset(b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/=")


def certificates_der(data: bytes) -> list[bytes]:
    """The DER bytes of every certificate block of a PEM certificate file, by one rule that
    the C++ client mirrors (`read_tls_ca`), so that both clients and the server refuse the same
    files; ValueError saying why (with its line number) otherwise: the file's form is
    `pem_blocks`'; a certificate block (CERTIFICATE_LABELS) decodes to one X.509 certificate
    (version 1 or 3) in strict DER (no bytes after it, no long-form lengths or other BER
    forms, times with their seconds: `der_problem`, `certificate_parts_problem`), each of its
    extensions readable and given once; the file holds at least one certificate."""
    out = [_certificate_der(der, opened) for label, der, opened in pem_blocks(data)
           if label in CERTIFICATE_LABELS]
    if not out:
        raise ValueError("no 'BEGIN CERTIFICATE' block")
    return out


def pem_blocks(data: bytes) -> list[tuple[str, bytes, int]]:
    """(label, decoded bytes, line number of its BEGIN) of each block of a PEM file (a
    certificate chain, trusted certificates or a private key), by the rule gRPC's TLS reads
    them with; ValueError saying why (with its line number) otherwise:
    - lines end at "\n" (a "\r" before it and trailing blanks are dropped); no control
      character but a tab anywhere (gRPC reads the file as a C string: a NUL ends it);
      text outside blocks (comments, `openssl x509 -text` output) is skipped;
    - a line starting "-----BEGIN LABEL-----" opens a block that a line "-----END LABEL-----"
      of the same label must close; a PEM marker after other text on a line is refused;
    - a block's body is base64 lines of at most MAX_PEM_LINE characters with no blank line
      among them and no "Name: value" headers (an encrypted block); a TRUSTED CERTIFICATE is
      refused."""
    out: list[tuple[str, bytes, int]] = []
    label, opened, body = None, 0, []
    for number, raw in enumerate(data.split(b"\n"), 1):
        line = raw.rstrip(b"\r").rstrip(b" \t")
        control = next((c for c in line if c < 0x20 and c != 0x09 or c == 0x7F), None)
        if control is not None:
            raise ValueError(f"line {number} holds a control character (0x{control:02x})")
        begin, end = line.startswith(b"-----BEGIN "), line.startswith(b"-----END ")
        if not (begin or end) and (b"-----BEGIN " in line or b"-----END " in line):
            raise ValueError(f"line {number} holds a PEM marker after other text")
        if label is None:
            if end:
                raise ValueError(f"line {number} ends a block that no BEGIN line opened")
            if begin:
                label, opened, body = _marker_label(line, b"-----BEGIN ", number), number, []
                if label == "TRUSTED CERTIFICATE":
                    raise ValueError(f"line {number} opens a TRUSTED CERTIFICATE block, which "
                                     "TLS here does not read: write it as a CERTIFICATE "
                                     "(openssl x509 -in FILE -out NEW)")
            continue
        if begin:
            raise ValueError(f"line {number} opens a block inside the one opened at line "
                             f"{opened}")
        if not end:
            width = len(raw.rstrip(b"\r"))
            if width > MAX_PEM_LINE:  # BoringSSL reads a line 253 bytes at a time
                raise ValueError(f"line {number} is {width} characters long; "
                                 f"a PEM line holds at most {MAX_PEM_LINE} (rewrite the file "
                                 "with `openssl x509 -in FILE -out NEW`)")
            body.append(line.strip())
            continue
        closing = _marker_label(line, b"-----END ", number)
        if closing != label:
            raise ValueError(f"line {number} ends '{closing}', but line {opened} opened "
                             f"'{label}'")
        named = "certificate" if label in CERTIFICATE_LABELS else label
        out.append((label, _body_base64(body, named, opened), opened))
        label = None
    if label is not None:
        raise ValueError(f"the block opened at line {opened} has no END line")
    return out


def _marker_label(line: bytes, prefix: bytes, number: int) -> str:
    """The LABEL of a marker line "PREFIX LABEL-----"; ValueError where it is not one."""
    label = line[len(prefix):]
    name = label[:-5]  # bytes.isalnum: ASCII letters and digits only, False when empty
    if not label.endswith(b"-----") or not name.replace(b" ", b"").isalnum():
        raise ValueError(f"line {number} is not a PEM marker line ('{prefix.decode()}LABEL-----')")
    return name.decode("ascii")


def _base64(text: bytes, label: str, opened: int) -> bytes:
    """The bytes of a block's base64 `text` (blanks removed); ValueError where it is not
    base64 (other characters, padding misplaced, a length not a multiple of 4)."""
    import binascii

    padding = len(text) - len(text.rstrip(b"="))
    if not text or not set(text) <= _BASE64 or len(text) % 4 or padding > 2 \
            or b"=" in text.rstrip(b"="):
        raise ValueError(f"the {label} block at line {opened} is not base64")
    return binascii.a2b_base64(text)


def _body_base64(body: list[bytes], label: str, opened: int) -> bytes:
    """The decoded base64 of a block's body lines (`label` names it in messages): base64 lines
    only, no blank line among them, no "Name: value" headers (an encrypted or annotated block:
    OpenSSL then reads its base64 only in 64-character lines, BoringSSL otherwise)."""
    block = f"the {label} block at line {opened}"
    if any(b":" in line for line in body):
        raise ValueError(f"{block} has PEM headers (an encrypted or annotated block), which "
                         "a certificate file does not hold")
    if b"" in body:
        raise ValueError(f"{block} has a blank line inside its base64")
    return _base64(b"".join(b"".join(line.split()) for line in body), label, opened)


def _certificate_der(der: bytes, opened: int) -> bytes:
    """`der` (the certificate block at line `opened`) if it is one X.509 certificate in strict
    DER."""
    problem = der_problem(der) or certificate_parts_problem(der)
    if problem:
        raise ValueError(f"the certificate block at line {opened} is not in strict DER "
                         f"({problem})")
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives.serialization import Encoding
    except ImportError:
        return der
    try:
        with warnings.catch_warnings():  # a serial number of 0 or below: taken, as OpenSSL does
            warnings.simplefilter("ignore")
            certificate = x509.load_der_x509_certificate(der)
            same = certificate.public_bytes(Encoding.DER) == der
            list(certificate.extensions)  # each parsed: a duplicate or malformed one refused
    except Exception as err:  # noqa: BLE001 - cryptography's parse errors, Rust-side ones
        reason = " ".join(str(err).split())[:160] or type(err).__name__
        raise ValueError(f"the certificate block at line {opened} is not an X.509 certificate "
                         f"({reason})") from None
    if not same:
        raise ValueError(f"the certificate block at line {opened} is not in strict DER (it "
                         "does not encode back to the same bytes)")
    return der


def _elements(data: bytes, start: int = 0, end: int | None = None):
    """(tag, where its value starts, where it ends) of each DER element in data[start:end];
    ValueError saying which length rule an element breaks (long-form tags, indefinite or
    non-shortest lengths, lengths over 4 bytes or past the end)."""
    at, end = start, len(data) if end is None else end
    while at < end:
        tag = data[at]
        if tag & 0x1F == 0x1F:
            raise ValueError("a tag in the long form")
        if at + 1 >= end:
            raise ValueError("an element cut short")
        size, at = data[at + 1], at + 2
        if size == 0x80:
            raise ValueError("an indefinite length")
        if size > 0x80:
            count = size & 0x7F
            if count > 4 or end - at < count:
                raise ValueError("a length cut short")
            if data[at] == 0:
                raise ValueError("a length not in its shortest form")
            size, at = int.from_bytes(data[at:at + count], "big"), at + count
            if size < 0x80:
                raise ValueError("a length not in its shortest form")
        if size > end - at:
            raise ValueError("an element cut short")
        yield tag, at, at + size
        at += size


def _time_problem(value: bytes, generalized: bool) -> bool:
    """Whether a UTCTime (YYMMDDHHMMSSZ) or GeneralizedTime (YYYYMMDDHHMMSSZ) is not a real
    instant written as DER writes it."""
    import calendar

    digits = 14 if generalized else 12
    if len(value) != digits + 1 or value[-1:] != b"Z" or not value[:-1].isdigit():
        return True
    two = [int(value[i:i + 2]) for i in range(0, digits, 2)]
    year = two[0] * 100 + two[1] if generalized else two[0] + (2000 if two[0] < 50 else 1900)
    month, day, hour, minute, second = two[-5:]
    return not (1 <= month <= 12 and 1 <= day <= calendar.monthrange(year, month)[1]
                and hour <= 23 and minute <= 59 and second <= 59)


def _bit_string_problem(value: bytes) -> bool:
    """Whether a BIT STRING's value breaks DER: unused bits over 7, or not 0."""
    return (not value or value[0] > 7 or len(value) == 1 and value[0] != 0
            or len(value) > 1 and value[-1] & ((1 << value[0]) - 1) != 0)


def der_problem(data: bytes, start: int = 0, end: int | None = None, depth: int = 32) -> str:
    """Why the DER elements in data[start:end] break a rule of DER that OpenSSL's reader lets
    through, or "": `_elements`' length rules, a string in constructed form, a BIT STRING
    whose unused bits are not 0, a time not a real instant with its seconds and Z, a BOOLEAN
    other than 0xFF (a FALSE is a DEFAULT, which DER leaves out), an INTEGER with a redundant
    leading byte. Constructed elements are read through, at most `depth` levels. The C++
    client's `der_problem` states the same rule."""
    if depth <= 0:
        return "nested too deeply"
    try:
        for tag, at, stop in _elements(data, start, end):
            value = data[at:stop]
            if tag & 0x20 and tag & 0xC0 == 0 and tag not in (0x30, 0x31):
                return "a string written in constructed form"
            if tag & 0x20:
                inner = der_problem(data, at, stop, depth - 1)
                if inner:
                    return inner
            elif tag == 0x03 and _bit_string_problem(value):
                return "a BIT STRING whose unused bits are not 0"
            elif tag in (0x17, 0x18) and _time_problem(value, tag == 0x18):
                return "a time not a real instant written with its seconds and Z"
            elif tag == 0x01 and value != b"\xff":
                return ("a BOOLEAN FALSE written out, which DER leaves out" if value == b"\x00"
                        else "a BOOLEAN TRUE not written as 0xFF")
            elif tag == 0x02 and (not value or len(value) > 1 and (
                    value[0] == 0 and not value[1] & 0x80 or value[0] == 0xFF and value[1] & 0x80)):
                return "an INTEGER not in its shortest form"
    except ValueError as err:
        return str(err)
    return ""


def certificate_parts_problem(der: bytes) -> str:
    """Why parts of a certificate that `der_problem` reads as plain bytes break DER, or "":
    the issuer's and subject's unique IDs ([1] and [2] of the signed part: BIT STRINGs) and
    each extension's value (DER inside its OCTET STRING). The C++ client reads the same."""
    try:
        _, body, end = next(_elements(der))
        _, tbs, tbs_end = next(_elements(der, body, end))
        for tag, at, stop in _elements(der, tbs, tbs_end):
            if tag in (0x81, 0x82) and _bit_string_problem(der[at:stop]):
                return "a unique ID whose unused bits are not 0"
            if tag != 0xA3:
                continue
            _, listed, listed_end = next(_elements(der, at, stop))
            for _, one, one_end in _elements(der, listed, listed_end):
                *_, (kind, value, value_end) = _elements(der, one, one_end)
                problem = kind == 0x04 and der_problem(der, value, value_end)
                if problem:
                    return f"an extension's value holds {problem}"
    except (ValueError, StopIteration):
        return ""  # the whole was checked by der_problem; a shape cryptography has read
    return ""


# OpenSSL's security bits a trusted certificate's key, and the signature of one not
# self-issued, must reach: its level 2, which the C++ client's OpenSSL holds chains to (RSA and
# DSA keys of 2048 bits, ECDSA curves of 224; no MD5 or SHA-1 signatures)
MIN_SECURITY_BITS = 112


def security_bits(key) -> int | None:
    """OpenSSL's security bits of a public key (EVP_PKEY_security_bits), None where unknown."""
    from cryptography.hazmat.primitives.asymmetric import dsa, ec, rsa

    if isinstance(key, (rsa.RSAPublicKey, dsa.DSAPublicKey)):
        size = key.key_size  # NIST SP 800-57's table, as OpenSSL reads it
        return next((bits for floor, bits in ((15360, 256), (7680, 192), (3072, 128),
                                              (2048, 112), (1024, 80)) if size >= floor), 0)
    if isinstance(key, ec.EllipticCurvePublicKey):
        return key.curve.key_size // 2
    return None


def trusted_certificates_problem(data: bytes) -> str | None:
    """Why a PEM file of certificates to trust (a client's `tls_ca`) holds one that the C++
    client's OpenSSL cannot anchor a chain in, or None; the C++ client applies the same rule:
    - a certificate that is not a CA by OpenSSL's rule (basicConstraints CA:TRUE and no key
      usage without keyCertSign; or, without basicConstraints, a key usage allowing
      keyCertSign) and not self-issued (issuer = subject): it can neither sign the server's
      certificate nor be the server's own self-signed one;
    - a key under MIN_SECURITY_BITS (RSA under 2048 bits), or, on a certificate not
      self-issued, a signature under them (MD5, SHA-1): gRPC's BoringSSL in the Python client
      takes such a chain, the C++ client's OpenSSL does not.
    (A self-signed certificate that is not a CA authenticates a server presenting it in both
    clients, and one it signed only in the Python client: BoringSSL takes such an issuer.)"""
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes
    except ImportError:
        return None
    for number, der in enumerate(certificates_der(data), 1):
        try:
            one = x509.load_der_x509_certificate(der)
            bits = security_bits(one.public_key())
            extensions = {e.oid: e.value for e in one.extensions}
        except Exception:  # noqa: BLE001 - parsed by certificates_der already
            continue
        which = f"certificate {number} ({one.subject.rfc4514_string()[:80]})"
        if bits is not None and bits < MIN_SECURITY_BITS:
            return (f"{which} has a key of {bits} security bits, under the "
                    f"{MIN_SECURITY_BITS} that OpenSSL clients hold a chain to (RSA: 2048 bits)")
        if one.issuer == one.subject:
            continue
        try:
            digest = one.signature_hash_algorithm
            digest = digest.name.upper() if isinstance(digest, (hashes.MD5, hashes.SHA1)) \
                else None
        except Exception:  # noqa: BLE001 - a digest cryptography does not know (MD2, MD4)
            digest = "a digest OpenSSL does not take"
        if digest:
            return (f"{which} is signed with {digest}, which OpenSSL clients refuse in a "
                    "chain")
        limits = extensions.get(x509.oid.ExtensionOID.BASIC_CONSTRAINTS)
        usage = extensions.get(x509.oid.ExtensionOID.KEY_USAGE)
        if limits is not None:
            ca = limits.ca and (usage is None or usage.key_cert_sign)
        else:
            ca = usage is not None and usage.key_cert_sign
        if not ca:
            return (f"{which} is neither a CA nor self-signed, so no client can anchor a chain "
                    "in it: give the CA certificate that signed it")
    return None
