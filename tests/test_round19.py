"""Issue 43, attack round 19 (service side): certificate files whose signed part is not strict
DER (the C++ client's OpenSSL keeps that part as received, so encoding it again proved
nothing), PEM text gRPC's own reader stops at (a NUL, a blank line inside base64, a ':' line
outside a block's headers), and chains whose intermediate may not sign certificates."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.io.pem import pem_problem
from slamreloc.service.server import certificate_problem
from tests.fuzzing import run_cli
from tests.test_round18 import der, make_certificate, pem

pytest.importorskip("cryptography")


# ---- a DER tree, to write a certificate's elements in forms DER forbids -------------------------
def parse_der(data: bytes) -> list:
    """DER bytes -> [(tag, children or value bytes)], constructed elements read through."""
    out, at = [], 0
    while at < len(data):
        tag, size = data[at], data[at + 1]
        at += 2
        if size & 0x80:
            n = size & 0x7F
            size = int.from_bytes(data[at:at + n], "big")
            at += n
        value = data[at:at + size]
        at += size
        out.append((tag, parse_der(value) if tag & 0x20 else value))
    return out


def write_der(tree: list, long_at: int | None = None, _count: list | None = None) -> bytes:
    """The tree as DER; the element numbered `long_at` (depth first, from 0) with its length
    in a long form DER forbids (BER)."""
    count = [0] if _count is None else _count
    out = b""
    for tag, body in tree:
        index = count[0]
        count[0] += 1
        value = write_der(body, long_at, count) if isinstance(body, list) else body
        n = len(value)
        if index == long_at:
            length = b"\x84" + n.to_bytes(4, "big")
        elif n < 0x80:
            length = bytes([n])
        else:
            raw = n.to_bytes((n.bit_length() + 7) // 8, "big")
            length = bytes([0x80 | len(raw)]) + raw
        out += bytes([tag]) + length + value
    return out


def count_elements(tree: list) -> int:
    return sum(1 + (count_elements(b) if isinstance(b, list) else 0) for _, b in tree)


def walk(tree: list):
    """Every (list holding it, index) of the tree's elements, depth first."""
    for i, (_, body) in enumerate(tree):
        yield tree, i
        if isinstance(body, list):
            yield from walk(body)


def non_der(certificate_der: bytes, form: str) -> bytes:
    """The certificate with one element written in a form DER forbids (the signature no longer
    matches: no reader here checks it)."""
    tree = parse_der(certificate_der)
    for holder, i in walk(tree):
        tag, body = holder[i]
        if form == "boolean 01" and tag == 0x01:
            holder[i] = (tag, b"\x01")
            break
        if form == "false written" and tag == 0x30 and isinstance(body, list) \
                and len(body) == 2 and body[0][0] == 0x06 and body[1][0] == 0x04:
            holder[i] = (tag, [body[0], (0x01, b"\x00"), body[1]])  # an extension, critical FALSE
            break
        if form == "integer padded" and tag == 0x02:
            holder[i] = (tag, b"\x00" + body)  # the version, then the serial number
            if body[0] & 0x80 == 0:
                break
        if form == "time without seconds" and tag == 0x17:
            holder[i] = (tag, body[:10] + b"Z")
            break
    else:
        raise AssertionError(f"no element for {form}")
    return write_der(tree)


@pytest.fixture(scope="module")
def certificate() -> bytes:
    from cryptography import x509

    return der(make_certificate(extensions=[
        (x509.BasicConstraints(ca=False, path_length=None), True),  # critical: a BOOLEAN
        (x509.SubjectKeyIdentifier(b"\x01" * 20), False)])[0])


@settings(max_examples=30, deadline=None)
@given(data=st.data())
def test_a_length_in_a_long_form_anywhere_is_refused(certificate, data):
    """W1: a long-form length inside the signed part (the issuer's, say) was taken by the C++
    client; by the one rule it is refused wherever it is."""
    n = count_elements(parse_der(certificate))
    at = data.draw(st.integers(0, n - 1))
    assert write_der(parse_der(certificate)) == certificate  # the codec itself is exact
    problem = pem_problem(pem(write_der(parse_der(certificate), long_at=at)), "certificate")
    assert problem is not None and "the certificate block at line 1" in problem, problem


@pytest.mark.parametrize("form", ["boolean 01", "false written", "integer padded",
                                  "time without seconds"])
def test_other_forms_der_forbids_are_refused(certificate, form):
    """W1: a BOOLEAN TRUE written 0x01, an explicit `critical FALSE`, a padded INTEGER and a
    UTCTime without seconds were taken by the C++ client (the last then failed every
    handshake)."""
    problem = pem_problem(pem(non_der(certificate, form)), "certificate")
    assert problem is not None and "the certificate block at line 1" in problem, problem


@pytest.mark.parametrize("text,words", [
    ("{a:blank}", "has a blank line inside its base64"),
    ("# note\x00 here\n{a}", "line 1 holds a control character (0x00)"),
    ("-----BEGIN FOO-----\nAAAA\nx:y\nAAAA\n-----END FOO-----\n{a}", "has PEM headers"),
    ("-----BEGIN FOO-----\nA: b\nAAAA\n-----END FOO-----\n{a}", "has PEM headers"),
    # round 20 (Y2): headers in another block, even well formed: OpenSSL then wants 64-column
    # base64 and loads no certificate after a block without it
    ("-----BEGIN FOO-----\nA: b\n\nAAAA\n-----END FOO-----\n{a}", "has PEM headers"),
    # round 20 (Y1): a line of 253 characters (BoringSSL reads 253 at a time: no root loaded)
    ("-----BEGIN FOO-----\n" + "A" * 252 + "=\n-----END FOO-----\n{a}", "253 characters long"),
])
def test_text_grpc_stops_reading_at_is_refused(certificate, text, words):
    """W2: a blank line inside base64, a NUL (gRPC reads the file as a C string), a ':' line
    in another block's base64 and headers with no blank line after them: gRPC's reader stops
    there and keeps only the certificates before, so a CA file loaded no root and a chain
    lost its intermediate. The rule refuses them, naming the line or block; since round 20
    any headers and any line over 76 characters too (Y1, Y2)."""
    good = pem(certificate).decode()
    lines = good.splitlines(keepends=True)
    blank = "".join(lines[:3] + ["\n"] + lines[3:])  # a blank line after 2 lines of base64
    problem = pem_problem(text.replace("{a:blank}", blank).replace("{a}", good).encode(),
                          "certificate")
    assert problem is not None and words in problem, problem
    fine = "-----BEGIN FOO-----\nAAAA\n-----END FOO-----\n" + good
    assert pem_problem(fine.encode(), "certificate") is None


@pytest.mark.parametrize("which", ["CA:FALSE", "no basicConstraints", "no keyCertSign"])
def test_a_chain_whose_intermediate_may_not_sign_is_refused(which):
    """W3: an intermediate with CA:FALSE, or a key usage without keyCertSign, started the
    server with TLS; every handshake then failed ("invalid CA certificate")."""
    from cryptography import x509

    flags = dict.fromkeys(("digital_signature", "content_commitment", "key_encipherment",
                           "data_encipherment", "key_agreement", "key_cert_sign", "crl_sign",
                           "encipher_only", "decipher_only"), False)
    root = make_certificate("root", ca=True, days=(-30, 30))
    extensions = {"CA:FALSE": [(x509.BasicConstraints(ca=False, path_length=None), True)],
                  "no basicConstraints": [],
                  "no keyCertSign": [(x509.BasicConstraints(ca=True, path_length=None), True),
                                     (x509.KeyUsage(**{**flags, "crl_sign": True}), True)]}
    intermediate = make_certificate("int", issuer=root, extensions=extensions[which])
    leaf, _ = make_certificate("localhost", issuer=intermediate)
    problem = certificate_problem(pem(der(leaf)) + pem(der(intermediate[0])))
    assert problem is not None and problem.startswith(
        "certificate 2 of its chain may not sign certificates"), problem


def test_a_ca_given_as_bytes_is_bounded_as_a_file_is():
    """Round 19 (minor): `Client(tls_ca=bytes)` took any size; a file of the same bytes was
    refused over 1 MiB."""
    from slamreloc.client import Client
    from slamreloc.errors import InputError

    with pytest.raises(InputError, match="over the 1048576 a PEM certificate may hold"):
        Client("127.0.0.1:1", tls_ca=b"#" * (2 << 20))


# ---- CLI side ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory):
    from tests.test_fuzz_inputs import _tiny_map

    return _tiny_map(tmp_path_factory.mktemp("round19") / "map")


def test_the_demo_viewer_reads_only_what_the_demo_wrote(tmp_path):
    """V1: the demo's viewer took every report*.json, poses_*.txt and traj*.txt of the
    workdir: a named pipe `report_zz.json` hung the demo at its end, a folder of that name
    failed it after every stage. It reads the demo's own outputs, by name."""
    import os

    from slamreloc.cli.demo import DEMO_REPORTS, DEMO_TRAJECTORIES, demo_viewer_inputs

    os.mkfifo(tmp_path / "report_zz.json")
    (tmp_path / "report_dir.json").mkdir()
    (tmp_path / "trajectory_notes.txt").write_text("mine\n")
    inputs = demo_viewer_inputs(tmp_path, tmp_path / "map", tmp_path / "scene")
    assert {p.name for p in inputs.reports} == set(DEMO_REPORTS) - {"report.json"}
    assert {p.name for p in inputs.trajectories} == set(DEMO_TRAJECTORIES)
    assert all(p.parent == tmp_path for p in [*inputs.reports, *inputs.trajectories])


def test_a_busy_last_port_is_one_line_not_a_viewer_that_never_starts(tiny_map):
    """V2: `view --port 65535` with that port busy: viser moved on to 65536, its thread died
    with OverflowError and the process waited for ever."""
    import socket

    with socket.socket() as held:
        try:
            held.bind(("127.0.0.1", 65535))
            held.listen()
        except OSError:  # in use already: the same case
            pass
        code, err = run_cli(["view", str(tiny_map), "--port", "65535"], hang_s=60)
    assert code == 2 and err.strip().splitlines()[-1] == (
        "error: --port 65535: in use, and so is every port above it up to 65535: give another "
        "(0: any free one)"), err


def test_a_reference_that_is_a_link_loop_is_one_line(tiny_map, scene_dir, tmp_path):
    """V3: `evaluate --reference LOOP` ended in `RuntimeError: Symlink loop` (round 18's fix
    missed the labels of the references)."""
    loop = tmp_path / "loop"
    loop.symlink_to(loop.name)
    code, err = run_cli(["evaluate", str(tiny_map), str(scene_dir), "--split", "seq-02",
                         "--method", "matching", "--reference", str(loop), "--report",
                         str(tmp_path / "r.json")])
    assert code == 2 and "Traceback" not in err and str(loop) in err.strip().splitlines()[-1]


def test_a_users_file_at_a_trajectorys_names_file_is_not_replaced(tiny_map, tmp_path):
    """Round 19 (minor): the names file beside a TUM output (a second name the user never
    typed) was replaced whenever its text read as 'stamp name' lines: a numbered to-do list,
    or a TUM trajectory named X.names.txt. Only a names file as slamreloc writes it is."""
    todo = tmp_path / "todo.names.txt"
    todo.write_text("1 buy milk\n2 call bob\n")
    code, err = run_cli(["export", str(tiny_map), "--tum", str(tmp_path / "todo.txt")])
    assert code == 2 and str(todo) in err.strip().splitlines()[-1], err
    assert todo.read_text() == "1 buy milk\n2 call bob\n"
    assert not (tmp_path / "todo.txt").exists()
    own = tmp_path / "own.txt"
    for _ in range(2):  # its own output, names file included, is replaced
        code, err = run_cli(["export", str(tiny_map), "--tum", str(own)])
        assert code == 0, err
