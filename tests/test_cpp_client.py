"""clients/cpp: the C++ client, built with CMake against the system's gRPC, run against a live
server: the same lines as `slamreloc localize` and the same poses as the Python client, to the
last digit; typed errors with exit status 2."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamreloc.client import Client
from slamreloc.errors import InputError
from slamreloc.datasets import load_dataset
from slamreloc.service.server import ServeConfig, start_server
from tests.fuzzing import run_cli_output

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "cpp-client-test-token-0123"
N_FRAMES = 5


def _missing_tools() -> list[str]:
    missing = [tool for tool in ("cmake", "g++", "protoc", "grpc_cpp_plugin", "pkg-config")
               if shutil.which(tool) is None]
    if "pkg-config" not in missing and subprocess.run(
            ["pkg-config", "--exists", "grpc++", "protobuf", "openssl"],
            check=False).returncode != 0:
        missing.append("pkg-config grpc++/protobuf/openssl (libgrpc++-dev, libprotobuf-dev, "
                       "libssl-dev)")
    return missing


MISSING = _missing_tools()
# checked before any fixture: without the tools, no scene or map is built for this module
pytestmark = pytest.mark.skipif(
    bool(MISSING), reason=f"the C++ client needs {', '.join(MISSING)} (Debian: libgrpc++-dev "
    "protobuf-compiler-grpc libprotobuf-dev protobuf-compiler cmake g++ pkg-config libssl-dev; "
    "scripts/install.sh installs them as root)")


@pytest.fixture(scope="module")
def server(small_map):
    running = start_server({"small": small_map.root},
                           ServeConfig(port=0, watch_s=0, token=TOKEN))
    yield running
    running.stop()


@pytest.fixture(scope="module")
def sequence(scene_dir, tmp_path_factory) -> Path:
    """A 7-Scenes sequence folder: the first query frames (colour, depth and pose files), and a
    featureless frame that cannot be localized."""
    out = tmp_path_factory.mktemp("cpp_seq") / "seq-02"
    out.mkdir()
    for frame in load_dataset(scene_dir).frames("seq-02")[:N_FRAMES]:
        stem = frame.image_path.name.removesuffix(".color.png")
        for path in frame.image_path.parent.glob(stem + ".*"):
            shutil.copy(path, out / path.name)
    grey = np.full((240, 320, 3), 128, np.uint8)
    cv2.imwrite(str(out / f"frame-{N_FRAMES:06d}.color.png"), grey)
    return out


def run_client(binary: Path, *args: str, env: dict | None = None, token: str | None = TOKEN):
    argv = [str(binary), *args] + (["--token", token] if token else [])
    environment = {**os.environ, **(env or {})}  # a variable given as None is unset
    return subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False,
                          env={k: v for k, v in environment.items() if v is not None})


def _fields(line: str) -> tuple[str, list[float], int]:
    parts = line.split()
    return parts[0], [float(v) for v in parts[1:8]], int(parts[8])


def test_lines_equal_slamreloc_localize_and_the_python_client(client_binary, server, small_map,
                                                              sequence):
    done = run_client(client_binary, "--server", server.address, "--map", "small",
                      str(sequence))
    assert done.returncode == 0 and done.stderr == "", done.stderr
    lines = done.stdout.splitlines()
    images = sorted(sequence.glob("frame-*.color.png"))
    assert len(lines) == len(images) == N_FRAMES + 1

    # `slamreloc localize` on the same files: the same names, outcomes and inlier counts; its
    # poses have 6 decimals
    status, out, err = run_cli_output(["localize", str(small_map.root), *map(str, images)])
    assert status == 0, err
    reference = out.splitlines()
    assert lines[-1] == reference[-1] == f"# frame-{N_FRAMES:06d}.color.png: not localized " \
                                         "(0 inliers)"
    with Client(server.address, token=TOKEN) as client:
        for line, ref, path in zip(lines[:-1], reference[:-1], images):
            name, pose, inliers = _fields(line)
            ref_name, ref_pose, ref_inliers = _fields(ref)
            assert (name, inliers) == (ref_name, ref_inliers) == (path.name, inliers)
            assert pose == pytest.approx(ref_pose, abs=6e-7)
            # the Python client's answer to the same bytes: every digit of the doubles
            r = client.localize(path, map="small").response
            t = r.world_from_cam
            assert r.localized and r.num_inliers == inliers
            assert pose == pytest.approx([t.tx, t.ty, t.tz, t.qx, t.qy, t.qz, t.qw], abs=1e-9,
                                         rel=0)


def test_tum_folder_camera_and_token_from_the_environment(client_binary, server, small_map,
                                                          sequence, tmp_path):
    """rgb.txt decides which images (in time order); --camera goes to the server (a lens
    other than the map's gives other poses, equal to the Python client's with that string)."""
    (tmp_path / "rgb").mkdir()
    names = [f"{1.5 + i:.6f}.png" for i in range(3)]
    for name, src in zip(names, sorted(sequence.glob("frame-*.color.png"))):
        shutil.copy(src, tmp_path / "rgb" / name)
    listed = [names[0], names[2]]  # names[1] is in rgb/ but not listed
    (tmp_path / "rgb.txt").write_text("# color images\n# timestamp filename\n\n" + "".join(
        f"{Path(n).stem} rgb/{n}\n" for n in listed))
    cam = small_map.camera
    camera = f"PINHOLE {cam.width} {cam.height} {cam.fx * 1.05} {cam.fy * 1.05} {cam.cx} {cam.cy}"
    done = run_client(client_binary, "--server", server.address, "--camera", camera,
                      str(tmp_path), env={"SLAMRELOC_TOKEN": TOKEN}, token=None)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert [line.split()[0] for line in lines] == listed
    with Client(server.address, token=TOKEN) as client:
        for line, name in zip(lines, listed):
            data = (tmp_path / "rgb" / name).read_bytes()
            _, pose, inliers = _fields(line)
            own = client.localize(data, camera=camera).response
            default = client.localize(data).response
            t = own.world_from_cam
            assert own.localized and own.num_inliers == inliers
            assert pose == pytest.approx([t.tx, t.ty, t.tz, t.qx, t.qy, t.qz, t.qw], abs=1e-9,
                                         rel=0)
            assert abs(pose[2] - default.world_from_cam.tz) + \
                abs(pose[0] - default.world_from_cam.tx) > 1e-4  # the camera made a difference


def _error_line(done: subprocess.CompletedProcess) -> str:
    assert done.returncode == 2, (done.returncode, done.stdout, done.stderr)
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), done.stderr
    return lines[0]


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_errors_name_the_file_or_server_and_exit_2(client_binary, server, sequence, tmp_path):
    address = server.address
    first = min(sequence.glob("frame-*.color.png"))
    # a map the server does not have: the first call fails, nothing is printed
    done = run_client(client_binary, "--server", address, "--map", "nosuch", str(sequence))
    line = _error_line(done)
    assert "NOT_FOUND (UNKNOWN_MAP)" in line and str(first) in line and address in line
    assert "nosuch" in line and done.stdout == ""
    # no token, and a wrong one
    for token in (None, "wrong-token-of-26-characters"):
        line = _error_line(run_client(client_binary, "--server", address, str(sequence),
                                      token=token, env={"SLAMRELOC_TOKEN": None}))
        assert "UNAUTHENTICATED" in line
    # a folder that does not exist, and one without images
    missing = tmp_path / "no_such_sequence"
    line = _error_line(run_client(client_binary, "--server", address, str(missing)))
    assert str(missing) in line
    line = _error_line(run_client(client_binary, "--server", address, str(tmp_path)))
    assert str(tmp_path) in line and "no images" in line
    # nobody listening
    dead = f"127.0.0.1:{_closed_port()}"
    line = _error_line(run_client(client_binary, "--server", dead, str(sequence)))
    assert dead in line and "UNAVAILABLE" in line
    # usage
    line = _error_line(run_client(client_binary, str(sequence)))
    assert "--server" in line
    # round 9, F9: a map name the server's rule refuses is refused before anything is sent
    for name, why in (("a\udcff", "not valid UTF-8"), ("a b", "space"), ("x" * 129, "128"),
                      ("", "empty")):
        line = _error_line(run_client(client_binary, "--server", address, "--map", name,
                                      str(sequence)))
        assert line.startswith("error: --map '") and why in line, line
    # round 9, F8: a NUL byte in rgb.txt is named with its line
    tum = tmp_path / "nul_tum"
    tum.mkdir()
    (tum / "rgb.txt").write_bytes(b"# list\n0.1 rgb/a\x00b.png\n")
    line = _error_line(run_client(client_binary, "--server", address, str(tum)))
    assert f"{tum / 'rgb.txt'}:2: image list holds a NUL byte" in line, line


def test_an_image_the_server_refuses_is_reported_and_the_rest_localized(client_binary, server,
                                                                        sequence, tmp_path):
    """As `slamreloc localize`: an error line for the bad file, the other lines, exit 2."""
    frames = sorted(sequence.glob("frame-*.color.png"))
    shutil.copy(frames[0], tmp_path / frames[0].name)
    bad = tmp_path / frames[1].name
    bad.write_bytes(frames[1].read_bytes()[:200])  # a truncated PNG
    shutil.copy(frames[2], tmp_path / frames[2].name)
    done = run_client(client_binary, "--server", server.address, str(tmp_path))
    line = _error_line(done)
    assert str(bad) in line and "BAD_IMAGE" in line
    assert [ln.split()[0] for ln in done.stdout.splitlines()] == [frames[0].name, frames[2].name]


def _self_signed(cert: Path, key: Path) -> None:
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
                    "-subj", "/CN=localhost", "-addext", "subjectAltName=IP:127.0.0.1",
                    "-keyout", str(key), "-out", str(cert)], check=True, capture_output=True)


def _pem(kind: str, der: bytes) -> bytes:
    """`der` armoured as a PEM block of `kind` (whatever the bytes are)."""
    import base64

    body = base64.encodebytes(der).decode()
    return f"-----BEGIN {kind}-----\n{body}-----END {kind}-----\n".encode()


def _certificate_pem() -> bytes:
    """A self-signed certificate (the `cryptography` package makes it)."""
    from datetime import datetime, timedelta, timezone

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "localhost")])
    now = datetime.now(timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(1).not_valid_before(now)
            .not_valid_after(now + timedelta(days=1)).sign(key, hashes.SHA256()))
    return cert.public_bytes(serialization.Encoding.PEM)


def test_tls(client_binary, small_map, sequence, tmp_path):
    """--tls-ca: the same answer over TLS; the server's certificate is checked."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl (to make a test certificate) not found")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    _self_signed(cert, key)
    frame = min(sequence.glob("frame-*.color.png"))
    (tmp_path / "seq").mkdir()
    shutil.copy(frame, tmp_path / "seq" / frame.name)
    running = start_server({"small": small_map.root}, ServeConfig(
        port=0, watch_s=0, token=TOKEN, tls_cert=cert, tls_key=key))
    try:
        done = run_client(client_binary, "--server", running.address, "--tls-ca", str(cert),
                          str(tmp_path / "seq"))
        assert done.returncode == 0, done.stderr
        name, pose, inliers = _fields(done.stdout)
        with Client(running.address, token=TOKEN, tls_ca=cert) as client:
            r = client.localize(frame).response
        t = r.world_from_cam
        assert name == frame.name and r.localized and r.num_inliers == inliers
        assert pose == pytest.approx([t.tx, t.ty, t.tz, t.qx, t.qy, t.qz, t.qw], abs=1e-9,
                                     rel=0)
        # plain TCP to a TLS server, and TLS trusting another certificate: refused
        line = _error_line(run_client(client_binary, "--server", running.address,
                                      str(tmp_path / "seq")))
        assert "UNAVAILABLE" in line
        other = tmp_path / "other.pem"
        _self_signed(other, tmp_path / "other.key")
        line = _error_line(run_client(client_binary, "--server", running.address, "--tls-ca",
                                      str(other), str(tmp_path / "seq")))
        assert "UNAVAILABLE" in line
    finally:
        running.stop()


def test_files_tokens_and_cameras_follow_the_python_rules(client_binary, server, sequence,
                                                          tmp_path):
    """The rules of the Python side (slamreloc.io.fileio, slamreloc.io.pem, token_problem):
    a pipe or a device is refused, never read (a pipe would block for ever); a CA file that is
    no PEM certificate, a token gRPC cannot carry or the server would refuse, and an empty
    option are refused before any call."""
    address = server.address
    fifo = tmp_path / "ca.fifo"
    os.mkfifo(fifo)
    zeros, bom = tmp_path / "zeros.pem", tmp_path / "bom.pem"
    zeros.write_bytes(bytes(4096))
    bom.write_bytes(b"\xef\xbb\xbf-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n")
    for ca, words in ((fifo, "a named pipe"), (Path("/dev/zero"), "a device"),
                      (tmp_path, "a folder"), (zeros, "line 1 holds a control character (0x00)"),
                      (bom, "byte-order mark"), (tmp_path / "none.pem", "not found")):
        line = _error_line(run_client(client_binary, "--server", address, "--tls-ca", str(ca),
                                      str(sequence)))
        assert str(ca) in line and "--tls-ca" in line and words in line, line
    garbage = tmp_path / "garbage.pem"
    garbage.write_text("-----BEGIN CERTIFICATE-----\nnot base64 !\n-----END CERTIFICATE-----\n")
    line = _error_line(run_client(client_binary, "--server", address, "--tls-ca", str(garbage),
                                  str(sequence)))
    assert str(garbage) in line and "the certificate block at line 1 is not base64" in line, line
    # round 17, T3: every certificate block is read, as the Python client reads them: a first
    # block that is no certificate (a key's bytes), and a good one then a broken one
    good = _certificate_pem()
    for blocks in ([_pem("CERTIFICATE", b"\x30\x03\x02\x01\x00")], [good, _pem("CERTIFICATE",
                                                                            b"garbage")]):
        ca = tmp_path / "blocks.pem"
        ca.write_bytes(b"".join(blocks))
        with pytest.raises(InputError):  # the Python client's rule
            Client(address, token=TOKEN, tls_ca=ca)
        line = _error_line(run_client(client_binary, "--server", address, "--tls-ca", str(ca),
                                      str(sequence)))
        assert str(ca) in line and "--tls-ca is not a PEM certificate" in line, line
        at = 1 + sum(block.count(b"\n") for block in blocks[:-1])  # the last block's line
        assert f"the certificate block at line {at} is not an X.509 certificate" in line, line
    port = address.rsplit(":", 1)[1]
    cases = [(["--tls-ca", ""], "--tls-ca: empty"), (["--camera", " "], "--camera: empty"),
             # the address and number rules of the Python side (target_problem, numbers)
             (["--server", f"127.0.0.1:{int(port) + 65536}"], "not a number from 1 to 65535"),
             (["--server", f"0177.0.0.1:{port}"], "short, octal or hexadecimal IPv4"),
             (["--timeout", "1e-4"], "out of 0.001 to 1e6"),
             (["--timeout", "0x10"], "not a number"), (["--timeout", " 5"], "not a number"),
             (["--token", " \t"], "--token: empty"),
             (["--token", "token with-a-space-0123"], "printable ASCII without spaces"),
             (["--token", "short"], "at least 16 characters")]
    for args, words in cases:
        server = [] if "--server" in args else ["--server", address]
        line = _error_line(run_client(client_binary, *server, *args, str(sequence), token=None))
        assert words in line, (args, line)
    # the variable: blanks around it dropped (as the server reads it), blank refused
    done = run_client(client_binary, "--server", address, str(sequence), token=None,
                      env={"SLAMRELOC_TOKEN": f"  {TOKEN}\n"})
    assert done.returncode == 0, done.stderr
    line = _error_line(run_client(client_binary, "--server", address, str(sequence),
                                  token=None, env={"SLAMRELOC_TOKEN": " "}))
    assert "$SLAMRELOC_TOKEN is empty" in line
    # an image that is a pipe: reported (never opened blocking), the others localized
    frames = sorted(sequence.glob("frame-*.color.png"))[:2]
    folder = tmp_path / "seq"
    folder.mkdir()
    shutil.copy(frames[0], folder / frames[0].name)
    os.mkfifo(folder / frames[1].name)
    done = run_client(client_binary, "--server", address, str(folder))
    line = _error_line(done)
    assert frames[1].name in line and "a named pipe" in line
    assert [ln.split()[0] for ln in done.stdout.splitlines()] == [frames[0].name]


@pytest.mark.parametrize("rows,words", [
    ("1.0 /etc/hostname\n", "points outside the dataset folder"),
    ("1.0 ../x.png\n", "points outside the dataset folder"),
    ("0x1 rgb/a.png\n", "is not a number"),
    ("1.0 rgb/a.png\n1.0 rgb/b.png\n", "repeats line 1 with another file"),
    ("2.0 rgb/a.png\n1.0 rgb/b.png\n", "2: timestamp 1.0 is earlier than line 1's"),
    ("1.0 rgb/a.png\n2.0 other/a.png\n", "listed more than once"),
    ("1e13 rgb/a.png\n", "timestamps are seconds")])
def test_rgb_txt_follows_the_tum_readers_rules(client_binary, server, tmp_path, rows, words):
    """rgb.txt as slamreloc.datasets.tum reads it: numbers by the number rule, files inside
    the folder, one file per timestamp, one image per name."""
    (tmp_path / "rgb.txt").write_text(rows)
    line = _error_line(run_client(client_binary, "--server", server.address, str(tmp_path)))
    assert str(tmp_path / "rgb.txt") in line and words in line, line


# pieces of a generated CA file: (name, bytes) built from two certificates `a` and `b`
def _ca_pieces(a: bytes, b: bytes) -> dict[str, bytes]:
    from tests.test_round18 import pem
    from tests.test_round19 import non_der, parse_der, write_der

    body = pem(a).decode().splitlines(keepends=True)
    return {
        "a long length inside": pem(write_der(parse_der(a), long_at=8)),
        **{f"a {form}": pem(non_der(a, form)) for form in (
            "boolean 01", "false written", "integer padded", "time without seconds")},
        "a blank in base64": "".join(body[:3] + ["\n"] + body[3:]).encode(),
        "nul comment": b"# note\x00 here\n", "form feed": b"\x0c\n",
        "other colon inside": b"-----BEGIN FOO-----\nAAAA\nx:y\n-----END FOO-----\n",
        "other headers": b"-----BEGIN FOO-----\nA: b\n\nAAAA\n-----END FOO-----\n",
        "other headers no blank": b"-----BEGIN FOO-----\nA: b\nAAAA\n-----END FOO-----\n",
        "a": pem(a), "b": pem(b), "a wide": pem(a, width=76), "a one line": pem(a, width=4096),
        "a x509 label": pem(a, "X509 CERTIFICATE"), "a trailing": pem(a + b"\x00\x01"),
        "a headers": pem(a, headers="Proc-Type: 4,ENCRYPTED\nDEK-Info: AES-128-CBC,00\n\n"),
        "a ber": pem(b"\x30\x83\x00" + a[2:]), "a cut": pem(a[:-5]),
        "a no end": pem(a).rsplit(b"-----END", 1)[0], "a trusted": pem(a, "TRUSTED CERTIFICATE"),
        "a bad char": pem(a).replace(b"A", b"*", 1), "a padding": pem(a).replace(b"\n-----E",
                                                                                  b"==\n-----E"),
        "key": pem(b"\x30\x03\x02\x01\x00", "PRIVATE KEY"),
        "key not base64": b"-----BEGIN PRIVATE KEY-----\nnot*base64\n-----END PRIVATE KEY-----\n",
        "comment": b"# a comment\n", "marker comment": b"# -----BEGIN CERTIFICATE----- see\n",
        "lone end": b"-----END CERTIFICATE-----\n", "odd marker": b"-----BEGIN x-y-----\n",
        "blank": b"\n", "crlf": b"\r\n", "trailing blanks": b" \t\n",
    }


def test_the_two_clients_read_ca_files_by_one_rule(client_binary, tmp_path_factory):
    """U1, U2 (attack round 18): the C++ client read --tls-ca with OpenSSL's PEM reader (which
    asked for a pass phrase on a block with headers, took bytes after a certificate, long-form
    lengths and a marker inside a comment, and refused a last block with no END that Python
    took). It now states the rule of slamreloc.io.pem.certificates_der: on generated files,
    each is refused by one client exactly when the other refuses it."""
    pytest.importorskip("cryptography")
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from slamreloc.io.pem import pem_problem, trusted_certificates_problem
    from tests.test_round18 import der, make_certificate, pem

    from cryptography import x509

    extensions = [(x509.BasicConstraints(ca=False, path_length=None), True),
                  (x509.SubjectKeyIdentifier(b"\x01" * 20), False)]
    pieces = _ca_pieces(der(make_certificate("c0", extensions=extensions)[0]),
                        der(make_certificate("c1")[0]))
    # round 20 (Y6): certificates signed by another, trusted as anchors: a CA's taken, any
    # other refused by both (`trusted_certificates_problem`)
    root = make_certificate("root", ca=True)
    signing = x509.KeyUsage(False, False, False, False, False, True, False, False, False)
    signed = {"leaf signed": {}, "ca signed": {"ca": True},
              "key usage signs": {"extensions": [(signing, True)]},
              "ca whose usage does not sign": {"ca": True, "extensions": [
                  (x509.KeyUsage(True, *[False] * 8), True)]}}
    for name, kwargs in signed.items():
        pieces[name] = pem(der(make_certificate(name.split()[0], issuer=root, **kwargs)[0]))
    folder = tmp_path_factory.mktemp("ca_rule")
    (folder / "seq").mkdir()
    port = _closed_port()

    @settings(max_examples=80, deadline=None, database=None)
    @given(st.lists(st.sampled_from(sorted(pieces)), min_size=1, max_size=4))
    def check(names):
        data = b"".join(pieces[n] for n in names)
        (folder / "ca.pem").write_bytes(data)
        done = run_client(client_binary, "--server", f"127.0.0.1:{port}", "--timeout", "2",
                          "--tls-ca", str(folder / "ca.pem"), str(folder / "seq"))
        refused = ("--tls-ca is not a PEM certificate" in done.stderr
                   or "--tls-ca cannot be trusted" in done.stderr)
        problem = pem_problem(data, "certificate") or trusted_certificates_problem(data)
        assert refused == (problem is not None), (names, problem, done.stderr)
        assert "pass phrase" not in done.stderr

    check()


def test_the_two_clients_read_the_same_der_inside_certificates(client_binary, tmp_path):
    """Round 20's open DER cases (tests/test_round21.py): a constructed string in a name, a
    unique ID's padding bits, BER inside an extension's value; and round 21's weak anchors
    (an RSA-1024 root, a SHA-1-signed intermediate): each refused by both clients with the
    same words, or taken by both."""
    pytest.importorskip("cryptography")
    from slamreloc.io.pem import pem_problem, trusted_certificates_problem
    from tests.test_round18 import pem
    from tests.test_round21 import crafted_certificates, weak_trusted_certificates

    (tmp_path / "seq").mkdir()
    port = _closed_port()
    cases = {name: (pem(data), words) for name, (data, words) in crafted_certificates().items()}
    for name, (data, words) in weak_trusted_certificates().items():  # round 21's Z4
        cases[name] = (data, words)
    for name, (data, words) in cases.items():
        (tmp_path / "ca.pem").write_bytes(data)
        done = run_client(client_binary, "--server", f"127.0.0.1:{port}", "--timeout", "2",
                          "--tls-ca", str(tmp_path / "ca.pem"), str(tmp_path / "seq"))
        problem = pem_problem(data, "certificate") or trusted_certificates_problem(data)
        if words is None:
            assert problem is None and "--tls-ca" not in done.stderr, (name, done.stderr)
        else:
            assert words in problem and words in done.stderr, (name, problem, done.stderr)
