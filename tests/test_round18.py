"""Issue 43, attack round 18 (service side): the PEM rule of certificate files, now stated
once (`slamreloc.io.pem.certificates_der`) and mirrored by the C++ client
(tests/test_cpp_client.py compares the two on generated files); certificate chains whose other
certificates no client can verify; the explicit-curve check reading the key, not the whole
certificate."""

from __future__ import annotations

import base64
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.io.pem import certificates_der, pem_problem
from slamreloc.service.server import certificate_problem
from tests.fuzzing import run_cli
from tests.test_fuzz_inputs import _tiny_map

pytest.importorskip("cryptography")


def make_certificate(subject: str = "localhost", issuer=None, days=(-1, 1), serial: int = 1,
                     extensions=(), ca: bool = False):
    """(certificate, key): an ECDSA P-256 certificate for `subject`, signed by `issuer` ((its
    certificate, its key), default itself), valid from now + days[0] to now + days[1],
    with `extensions` ((extension, critical) pairs)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)])
    signer_name, signer_key = (name, key) if issuer is None else (issuer[0].subject, issuer[1])
    now = datetime.now(timezone.utc)
    builder = (x509.CertificateBuilder().subject_name(name).issuer_name(signer_name)
               .public_key(key.public_key()).serial_number(serial)
               .not_valid_before(now + timedelta(days=days[0]))
               .not_valid_after(now + timedelta(days=days[1])))
    if ca:
        builder = builder.add_extension(x509.BasicConstraints(ca=True, path_length=None), True)
    for extension, critical in extensions:
        builder = builder.add_extension(extension, critical)
    return builder.sign(signer_key, hashes.SHA256()), key


def pem(der: bytes, label: str = "CERTIFICATE", width: int = 64, headers: str = "") -> bytes:
    """`der` armoured as a PEM block of `label`, base64 lines of `width` characters."""
    text = base64.b64encode(der).decode()
    lines = [text[i:i + width] for i in range(0, len(text), width)]
    return (f"-----BEGIN {label}-----\n{headers}" + "\n".join(lines)
            + f"\n-----END {label}-----\n").encode()


def der(certificate) -> bytes:
    from cryptography.hazmat.primitives.serialization import Encoding

    return certificate.public_bytes(Encoding.DER)


@pytest.fixture(scope="module")
def two() -> list[bytes]:
    return [der(make_certificate(f"c{i}")[0]) for i in range(2)]


@settings(max_examples=40, deadline=None)
@given(width=st.integers(1, 18).map(lambda w: w * 4), crlf=st.booleans(),
       blanks=st.sampled_from(["", " ", "\t", " \t "]),
       comment=st.sampled_from(["", "# a comment\n", "subject=CN = c0\n", "Certificate:\n"]),
       other=st.sampled_from([None, "PRIVATE KEY", "X509 CRL"]),
       label=st.sampled_from(["CERTIFICATE", "X509 CERTIFICATE"]))
def test_a_certificate_file_in_any_layout_the_rule_allows_reads_as_its_certificates(
        two, width, crlf, blanks, comment, other, label):
    """Any line width up to 72 (76 with blanks), CRLF line ends, trailing blanks, text between
    blocks and blocks of other labels: the certificates come back, byte for byte, in order."""
    parts = [comment.encode(), pem(two[0], label, width)]
    if other is not None:
        parts.append(pem(b"\x30\x03\x02\x01\x00", other, width))
    parts.append(pem(two[1], "CERTIFICATE", width))
    data = b"".join(parts)
    if blanks:
        data = data.replace(b"\n", blanks.encode() + b"\n")
    if crlf:
        data = data.replace(b"\n", b"\r\n")
    assert certificates_der(data) == two


@settings(max_examples=40, deadline=None)
@given(extra=st.binary(min_size=1, max_size=16), at=st.integers(0, 1))
def test_bytes_after_a_certificate_inside_its_block_are_refused(two, extra, at):
    """U2: a certificate with bytes appended inside its base64 was taken by the C++ client
    (OpenSSL reads the certificate and ignores the rest), refused by Python's. Refused by the
    one rule, naming the block."""
    blocks = [pem(d) for d in two]
    blocks[at] = pem(two[at] + extra)
    line = 1 if at == 0 else 1 + blocks[0].count(b"\n")
    problem = pem_problem(b"".join(blocks), "certificate")
    assert problem is not None and f"block at line {line}" in problem, problem


@pytest.mark.parametrize("layout,words", [
    ("headers", "has PEM headers"),  # U1: the C++ client asked for a pass phrase
    ("ber", "not"),  # a long-form length: not strict DER
    ("marker in text", "line 1 holds a PEM marker after other text"),
    ("no end", "has no END line"),  # the Python client took a last block with no END
    ("trusted", "TRUSTED CERTIFICATE block"),
    ("nested", "opens a block inside the one opened at line 1"),
    ("key not base64", "the PRIVATE KEY block at line"),
])
def test_the_files_the_two_clients_read_differently_are_refused_by_both(two, layout, words):
    """U1, U2: the files round 18 found that one client took and the other refused; each is
    refused by the one rule with a reason."""
    good = pem(two[0])
    if layout == "headers":
        data = pem(two[0], headers="Proc-Type: 4,ENCRYPTED\nDEK-Info: AES-128-CBC,00\n\n")
    elif layout == "ber":  # the outer SEQUENCE's length in a 3-byte long form
        d = two[0]
        assert d[1] == 0x82
        data = pem(b"\x30\x83\x00" + d[2:])
    elif layout == "marker in text":
        data = b"# -----BEGIN CERTIFICATE----- see below\n" + good
    elif layout == "no end":
        data = good + pem(two[1]).rsplit(b"-----END", 1)[0]
    elif layout == "trusted":
        data = good + pem(two[1], "TRUSTED CERTIFICATE")
    elif layout == "nested":
        data = b"-----BEGIN CERTIFICATE-----\n" + pem(two[1])
    else:
        data = good + b"-----BEGIN PRIVATE KEY-----\nnot*base64\n-----END PRIVATE KEY-----\n"
    problem = pem_problem(data, "certificate")
    assert problem is not None and words in problem, problem


def test_a_chain_with_a_certificate_no_client_can_verify_is_refused():
    """U3: a chain whose intermediate had expired, and a certificate marking critical an
    extension verifiers do not know, started the server "listening (TLS)"; every client's
    handshake then failed (the C++ client's OpenSSL: "unhandled critical extension"). The last
    certificate of a chain is only warned of (round 20, Y8)."""
    from cryptography import x509
    from cryptography.x509.oid import ObjectIdentifier

    root = make_certificate("root", ca=True, days=(-30, 30))
    expired = make_certificate("int", issuer=root, ca=True, days=(-30, -10))
    valid = make_certificate("int", issuer=root, ca=True, days=(-30, 30))
    for intermediate, fine in ((expired, False), (valid, True)):
        leaf, _ = make_certificate("localhost", issuer=intermediate)
        chain = pem(der(leaf)) + pem(der(intermediate[0])) + pem(der(root[0]))
        problem = certificate_problem(chain)
        assert (problem is None) == fine, problem
        if not fine:
            assert problem.startswith("certificate 2 of its chain expired on"), problem
    # round 20 (Y8): the last certificate expired may be a cross-signed root (AddTrust's
    # shape) that clients trusting the root never use: warned of, not refused
    other = make_certificate("other root", ca=True, days=(-90, 90))
    cross = make_certificate("root", issuer=other, ca=True, days=(-60, -10))
    leaf, _ = make_certificate("localhost", issuer=valid)
    with pytest.warns(UserWarning, match="certificate 3 of its chain expired on .* trusts its"):
        assert certificate_problem(pem(der(leaf)) + pem(der(valid[0]))
                                   + pem(der(cross[0]))) is None
    unknown = x509.UnrecognizedExtension(ObjectIdentifier("1.2.3.4.5.6.7"), b"\x05\x00")
    critical, _ = make_certificate(extensions=[(unknown, True)])
    assert "marks critical an extension TLS clients do not handle (1.2.3.4.5.6.7)" in \
        certificate_problem(pem(der(critical)))
    plain, _ = make_certificate(extensions=[(unknown, False)])  # not critical: ignored
    assert certificate_problem(pem(der(plain))) is None


def test_a_serial_number_holding_the_ec_key_oid_is_not_an_explicit_curve():
    """m1: the explicit-curve check searched the whole certificate for id-ecPublicKey, so a
    P-256 certificate whose serial number holds those bytes was refused (gRPC takes it)."""
    crafted, _ = make_certificate(serial=0x0106072A8648CE3D02013001)
    assert certificate_problem(pem(der(crafted))) is None


def test_a_tls_certificate_with_pem_headers_is_refused_in_one_line(tmp_path):
    """m2: a --tls-cert whose block had PEM headers passed the check (`cryptography` reads
    it) and gRPC refused it with three log lines before the error line."""
    from cryptography.hazmat.primitives import serialization

    certificate, key = make_certificate()
    (tmp_path / "key.pem").write_bytes(key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption()))
    (tmp_path / "cert.pem").write_bytes(pem(der(certificate), headers="Comment: mine\n\n"))
    code, err = run_cli(["serve", str(_tiny_map(tmp_path / "map")), "--port", "0", "--watch",
                         "0", "--tls-cert", str(tmp_path / "cert.pem"), "--tls-key",
                         str(tmp_path / "key.pem")], hang_s=60)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "has PEM headers" in lines[0], err
    assert str(tmp_path / "cert.pem") in lines[0]


# ---- CLI side ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round18") / "map")


def test_a_trajectory_of_no_poses_is_shown_as_an_empty_layer(small_map, tmp_path):
    """R1: round 17's Q5 let view read a trajectory of no poses (a session that never
    anchored writes one), but drawing it ended in viser's AssertionError (a traceback). It is
    a layer that says it has no poses."""
    import socket

    from slamreloc.viewer import ViewerInputs, build_scene, load_scene_data, make_server

    empty = tmp_path / "t.tum"
    empty.write_text("# timestamp tx ty tz qx qy qz qw\n")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = make_server("127.0.0.1", port)
    try:
        handles = build_scene(server, load_scene_data(ViewerInputs(small_map.root,
                                                                   trajectories=[empty])))
        names = list(handles.layers)
        handles.stop()
    finally:
        server.stop()
    assert "estimate: t (no poses)" in names, names


@pytest.mark.parametrize("args", [
    ["export", "{map}", "--tum", "{loop}"],
    ["export", "{map}", "--colmap", "{loop}"],
    ["export", "{map}", "--tum", "{loop}/x.tum"],
    ["map", "{scene}", "--out", "{loop}"],
    ["evaluate", "{map}", "{loop}", "--report", "{tmp}/r.json"],
    ["evaluate", "{map}", "{scene}", "--poses", "{loop}", "--report", "{tmp}/r.json"],
    ["demo", "--workdir", "{loop}", "--no-viewer"],
])
def test_a_symbolic_link_loop_at_an_input_or_output_is_one_line(tiny_map, scene_dir, tmp_path,
                                                                args):
    """R2: a link loop at an output path (or an input compared with the outputs) ended in
    `RuntimeError: Symlink loop` (a traceback, exit 1) from every writing command."""
    loop = tmp_path / "loop"
    loop.symlink_to(loop.name)
    argv = [a.format(map=tiny_map, loop=loop, scene=scene_dir, tmp=tmp_path) for a in args]
    code, err = run_cli(argv)
    lines = err.strip().splitlines()
    assert code == 2 and "Traceback" not in err and lines[-1].startswith(f"error: {loop}"), err
    assert "symbolic link" in lines[-1], lines[-1]


@pytest.mark.parametrize("name", ["report.json", "report_pseudo_label.json",
                                  "report_regressor.json", "poses_matching.txt",
                                  "trajectory_slam.names.txt", "map_updated"])
def test_demo_refuses_a_users_file_at_any_of_its_outputs_before_any_work(tmp_path, name):
    """R3: demo replaced a user's report.json and report_pseudo_label.json in its workdir
    unchecked, and refused a user's report_regressor.json only after rendering and training.
    Every demo output is checked by its command's rule before the scene is rendered."""
    workdir = tmp_path / "w"
    workdir.mkdir()
    user = workdir / name
    if name == "map_updated":
        user.mkdir()
        (user / "notes.txt").write_text("mine")
        user = user / "notes.txt"
    else:
        user.write_text('{"mine": "user data"}\n')
    code, err = run_cli(["demo", "--workdir", str(workdir), "--no-viewer"], hang_s=120)
    assert code == 2 and f"the demo's {name.replace('.names.txt', '.txt')}" in err, err
    assert user.read_text().startswith(("mine", '{"mine"'))
    assert not (workdir / "scene").exists()  # nothing rendered


def test_sfm_refuses_a_webp_photo_named_as_a_jpeg(tmp_path):
    """R4: the WebP refusal of round 17 went by the name; a WebP saved as .jpg (a web
    download) was read by OpenCV, then dropped by COLMAP as "not registered". Photos are
    taken by content."""
    import cv2
    import numpy as np

    photos = tmp_path / "photos"
    photos.mkdir()
    image = np.random.default_rng(0).integers(0, 255, (48, 64, 3), np.uint8)
    for i in range(3):
        cv2.imwrite(str(photos / f"p{i}.png"), image)
    ok, webp = cv2.imencode(".webp", image)
    assert ok
    (photos / "p3.jpg").write_bytes(webp.tobytes())
    code, err = run_cli(["sfm", str(photos), "--out", str(tmp_path / "o")])
    assert code == 2 and err.strip().splitlines()[-1] == (
        f"error: {photos / 'p3.jpg'}: a WebP image by its content (whatever its name), a "
        "format sfm does not read (PNG, JPEG, BMP, TIFF and PNM are read): convert it, or "
        "move it out"), err
    assert not (tmp_path / "o").exists()


def test_an_os_error_names_its_file_first(tiny_map, scene_dir, tmp_path, monkeypatch):
    """Round 18 (minor): a full disk was `error: [Errno 28] No space left on device: 'fs/mm'`,
    where every other error line names its file first."""
    import errno

    from slamreloc.cli import jobs

    def no_space(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(jobs, "write_json", no_space)
    report = tmp_path / "r.json"
    code, err = run_cli(["evaluate", str(tiny_map), str(scene_dir), "--split", "seq-02",
                         "--method", "matching", "--report", str(report)])
    assert code == 2 and err.strip().splitlines()[-1] == (
        f"error: {report}: No space left on device"), err


def test_a_json_depth_bound_the_parser_cannot_reach_is_refused(tiny_map, tmp_path):
    """Round 18 (minor): `--limit max_json_depth=10000` was taken, but the parser stops near
    1000 levels ("nested too deeply", without the bound's words): the bound is at most 500,
    and a deeper file is refused by the bound's message whatever its depth."""
    code, err = run_cli(["--limit", "max_json_depth=10000", "view", str(tiny_map)])
    assert code == 2 and "at most 500 (the JSON parser itself stops" in err, err
    for depth in (100, 5000):
        deep = tmp_path / f"deep{depth}.json"
        deep.write_text("[" * depth + "]" * depth)
        code, err = run_cli(["view", str(tiny_map), "--report", str(deep), "--port", "0"])
        line = err.strip().splitlines()[-1]
        assert code == 2 and "nested more than 64 levels deep" in line, err


@pytest.mark.parametrize("kind", ["fifo", "folder", "user file"])
def test_a_lock_path_the_writer_would_refuse_is_refused_before_the_work(tiny_map, tmp_path,
                                                                      kind):
    """Round 18 (minor): a FIFO, a folder or a user's file at `.NAME.lock` was refused only
    once the writer took its lock, after the work (`export --colmap` coloured every point
    first). It is refused with the outputs' checks, and the user's file is kept."""
    import os

    lock = tmp_path / ".ex.lock"
    if kind == "fifo":
        os.mkfifo(lock)
    elif kind == "folder":
        lock.mkdir()
    else:
        lock.write_text("2024\nbudget\n")
    code, err = run_cli(["export", str(tiny_map), "--colmap", str(tmp_path / "ex")])
    assert code == 2 and err.strip().splitlines()[-1].startswith(f"error: {lock}: "), err
    assert not (tmp_path / "ex").exists()
    if kind == "user file":
        assert lock.read_text() == "2024\nbudget\n"
