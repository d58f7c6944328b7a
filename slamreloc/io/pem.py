"""PEM files for TLS (`serve --tls-cert/--tls-key`, a client's trusted CA): one reader and
one rule for the server, the Python client and (mirrored) the C++ client."""

from __future__ import annotations

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
    problem = pem_problem(data, what)
    if problem:
        where = f"{path}: " if path is not None else ""
        raise InputError(f"{where}`{setting}` is not a PEM {what} ({problem})")
    return data


def pem_problem(data: bytes, what: str) -> str | None:
    """Why `data` is not a PEM `what` ("private key" or "certificate"), or None."""
    marker = b"PRIVATE KEY-----" if what == "private key" else b"-----BEGIN CERTIFICATE-----"
    if data.startswith(b"\xef\xbb\xbf"):  # Python's parsers skip it, gRPC's TLS does not
        return ("it starts with a UTF-8 byte-order mark, which gRPC's TLS does not read: save "
                "it without")
    if marker not in data:
        return "no " + ("'PRIVATE KEY'" if what == "private key" else "'BEGIN CERTIFICATE'") \
            + " block"
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives.serialization import load_pem_private_key
    except ImportError:
        return None
    try:
        if what == "private key":
            load_pem_private_key(data, password=None)
        else:
            x509.load_pem_x509_certificates(data)
    except (ValueError, TypeError) as err:  # cryptography's parse errors
        return " ".join(str(err).split())[:200] or type(err).__name__
    except Exception as err:  # noqa: BLE001 - an unsupported algorithm, a Rust-side error
        return f"{type(err).__name__}: {' '.join(str(err).split())[:200]}"
    return None
