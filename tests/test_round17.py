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
from tests.test_poses import wide_console

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


# ---- CLI side ----------------------------------------------------------------------------------
def test_output_paths_with_markup_are_shown_as_given(tiny_map, tmp_path):
    """Q4: `export --tum 'a[/x].tum'` wrote its file, then ended in rich's MarkupError (a
    traceback, exit 1); `[red]z.tum` and `x:smile:.tum` were shown as other names. The
    success line names the file as given."""
    for name in ("a[/x].tum", "[red]z.tum", "x:smile:.tum"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        with wide_console(400):  # rich folds at 80 columns, within a long path too
            code, err = run_cli(["export", str(tiny_map), "--tum", str(tmp_path / name)])
        assert code == 0 and (tmp_path / name).is_file(), err
        assert f"cameras to {tmp_path / name}" in " ".join(err.split()), err


def test_a_limit_no_read_could_use_is_refused_and_a_large_one_reads(tiny_map, tmp_path):
    """Q7: `--limit max_image_bytes=9223372036854775807` ended in OverflowError (a
    traceback): a read asked for a buffer of the bound's size. A bound is at most 2**48, and
    a read takes a buffer of the file's size, whatever the bound."""
    import cv2
    import numpy as np

    code, err = run_cli(["--limit", "max_image_bytes=9223372036854775807", "localize",
                         str(tiny_map), "x.png"])
    assert code == 2 and err.strip().splitlines()[-1] == (
        "error: slamreloc --limit 'max_image_bytes=9223372036854775807': at most "
        "281474976710656 (2**48: no input of that size can be read here), got "
        "9223372036854775807"), err
    for suffix in (".png", ".webp"):  # a header read, and a whole-file read
        image = tmp_path / f"q{suffix}"
        cv2.imwrite(str(image), np.zeros((48, 64, 3), np.uint8))
        code, err = run_cli(["--limit", f"max_image_bytes={1 << 48}", "--limit",
                             f"max_text_bytes={1 << 48}", "localize", str(tiny_map), str(image),
                             "--method", "matching"])
        assert code == 0, err


def test_error_lines_keep_a_names_blanks_and_escape_its_control_characters(tiny_map, tmp_path):
    """Q9: an error line folded a name's whitespace (`a  b.png` shown as `a b.png`, another
    file; a tab as a space); Q3: localize's per-image error printed a name's line break (two
    lines) and ESC sequences raw. Both are one line, the name as it is, its control
    characters as escapes."""
    code, err = run_cli(["localize", str(tiny_map), str(tmp_path / "a  b.png")])
    assert code == 2 and f"{tmp_path}/a  b.png" in err.strip().splitlines()[-1], err
    code, err = run_cli(["localize", str(tiny_map), str(tmp_path / "a\tb.png")])
    assert code == 2 and f"{tmp_path}/a\\tb.png" in err.strip().splitlines()[-1], err
    odd = tmp_path / "x\n\x1b[31mnone.png"
    odd.write_bytes(b"not an image")
    code, err = run_cli(["localize", str(tiny_map), str(odd)])
    errors = [line for line in err.splitlines() if "none.png" in line]
    assert len(errors) == 1 and "x\\n\\x1b[31mnone.png" in errors[0], err
    assert "\x1b" not in err


def test_sfm_refuses_photos_colmap_cannot_read_and_a_scale_under_its_bound(tmp_path):
    """Q1: WebP photos passed the format check, then COLMAP read none ("registered only 0 of
    10 images ... too little overlap"); Q8: `--scale 1e-300` was taken (camera centres of
    3e-300 m; map then labelled nothing). Both are refused before any work."""
    import cv2
    import numpy as np

    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        cv2.imwrite(str(photos / f"p{i}.png"), np.zeros((48, 64, 3), np.uint8))
    cv2.imwrite(str(photos / "p3.webp"), np.zeros((48, 64, 3), np.uint8))
    code, err = run_cli(["sfm", str(photos), "--out", str(tmp_path / "o")])
    assert code == 2 and err.strip().splitlines()[-1] == (
        f"error: {photos / 'p3.webp'}: a photo of a format sfm does not read (PNG, JPEG, BMP, "
        "TIFF and PNM are read): convert it, or move it out"), err
    (photos / "p3.webp").unlink()
    code, err = run_cli(["sfm", str(photos), "--out", str(tmp_path / "o"), "--scale", "1e-300"])
    assert code == 2 and "--scale must be metres per SfM unit, over 1e-6 and under 1e6" in err
    assert not (tmp_path / "o").exists()


def test_a_video_cut_short_is_refused(tmp_path):
    """Q10: a video whose file was cut short was read up to the cut, unsaid (3 of 40
    frames, then "SfM needs at least 2 images"; a longer cut ran SfM on what was left)."""
    import cv2
    import numpy as np

    from slamreloc.errors import InputError
    from slamreloc.io.video import video_frames

    video = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    rng = np.random.default_rng(0)
    for _ in range(40):
        writer.write(rng.integers(0, 255, (48, 64, 3), np.uint8))
    writer.release()
    assert len(list(video_frames(video, 10))) == 40
    cut = tmp_path / "cut.avi"
    cut.write_bytes(video.read_bytes()[: video.stat().st_size // 3])
    with pytest.raises(InputError, match=r"cut\.avi: only \d+ of the 40 frames its header "
                                         "declares could be read: the file is cut short"):
        list(video_frames(cut, 10))


def test_a_trajectory_of_no_poses_is_read_where_it_can_be(small_map, scene_dir, tmp_path):
    """Q5: `slam --trajectory T` from a session that never anchored writes a TUM file of no
    poses, which `view --trajectory` refused. view shows it as a trajectory of none (as it
    does when a report names it); `slam --odometry` still refuses it, saying why."""
    from slamreloc.viewer.data import ViewerInputs
    from slamreloc.viewer.loaders import load_scene_data

    empty = tmp_path / "t.tum"
    empty.write_text("# timestamp tx ty tz qx qy qz qw\n")
    data = load_scene_data(ViewerInputs(small_map.root, trajectories=[empty]))
    assert [len(t.poses) for t in data.trajectories] == [0]
    code, err = run_cli(["slam", str(scene_dir), "--map", str(small_map.root), "--report",
                         str(tmp_path / "r.json"), "--split", "seq-02", "--odometry", str(empty)])
    assert code == 2 and err.strip().splitlines()[-1] == (
        f"error: {empty}: no poses (expected lines 'name tx ty tz qx qy qz qw' or 'timestamp "
        "tx ty tz qx qy qz qw', or a COLMAP model folder)"), err


def test_a_map_is_not_extended_by_another_datasets_frames_of_its_names(small_map, scene_dir,
                                                                         tmp_path):
    """Q6: `slam OTHER --map M --out N` with OTHER another dataset whose frames are named as
    M's recorded N's dataset as OTHER only, so `export --ply` coloured M's points from
    OTHER's images of the same names. Refused before the session, naming both; a session of
    the map's own dataset extends it."""
    other = tmp_path / "other"
    shutil.copytree(scene_dir, other)
    out = tmp_path / "n"
    code, err = run_cli(["slam", str(other), "--map", str(small_map.root), "--out", str(out),
                         "--report", str(tmp_path / "r.json"), "--split", "seq-02"])
    last = err.strip().splitlines()[-1]
    assert code == 2 and last.startswith(f"error: {other}: holds frames named as the map "
                                         f"{small_map.root}'s own (such as 'seq-01/"), err
    assert f"which come from the map's dataset ({scene_dir.resolve()})" in last, last
    assert not out.exists() and not (tmp_path / "r.json").exists()
