"""Attack round 26 (A), E1 and E5: the C++ client and the Python side follow one rule.

E1: rgb.txt is read by one line rule (`slamreloc.io.fileio.plain_lines`): UTF-8 (a leading
byte-order mark dropped), lines ending at "\\n" (a "\\r" before it dropped), fields separated by
spaces or tabs only, any other control character or blank refused naming the file and line. The
C++ client read lines with std::getline and fields with `>>` (other blanks, no UTF-8 check);
Python with str.splitlines and str.split (every Unicode line break and blank). Each variant is
read by both here: both take the same frames, or both refuse it with the same message.
E5: an option given twice is refused by the C++ client as by the Python CLI."""

from __future__ import annotations

import re
import subprocess
import unicodedata
from concurrent import futures
from pathlib import Path
from urllib.parse import unquote

import cv2
import grpc
import numpy as np
import pytest

from slamreloc.datasets.tum import load_tum
from slamreloc.errors import InputError
from slamreloc.geometry import read_tum_trajectory
from slamreloc.io.fileio import plain_lines
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto import relocalizer_pb2_grpc as pb_grpc
from slamreloc.proto.messages import map_name_problem
from tests.fuzzing import run_cli_output
from tests.test_cpp_client import MISSING

needs_cpp = pytest.mark.skipif(
    bool(MISSING), reason=f"the C++ client needs {', '.join(MISSING)} (Debian: libgrpc++-dev "
    "protobuf-compiler-grpc libprotobuf-dev protobuf-compiler cmake g++ pkg-config libssl-dev)")


class _NotLocalized(pb_grpc.RelocalizerServicer):
    """A server that answers every Localize "not localized": the C++ client then prints one
    line per image it sent, in its order."""

    def Localize(self, request, context):
        return pb.LocalizeResponse(localized=False, num_inliers=0)


@pytest.fixture(scope="module")
def fake_server():
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
    pb_grpc.add_RelocalizerServicer_to_server(_NotLocalized(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    yield f"127.0.0.1:{port}"
    server.stop(None)


def _tum_folder(root: Path, rgb_txt: bytes) -> Path:
    """A TUM folder: rgb/a.png, rgb/b.png, rgb/c.png (small textured images), intrinsics.txt
    and the rgb.txt given."""
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for name in ("a", "b", "c"):
        cv2.imwrite(str(root / "rgb" / f"{name}.png"),
                    rng.integers(0, 255, (240, 320, 3), dtype=np.uint8))
    (root / "intrinsics.txt").write_text("262.5 0 159.5\n0 262.5 119.5\n0 0 1\n")
    (root / "rgb.txt").write_bytes(rgb_txt)
    return root


def _python(root: Path) -> tuple[list[str] | None, str | None]:
    """(the frames load_tum reads, None) or (None, its message)."""
    try:
        ds = load_tum(root)
    except InputError as err:
        return None, str(err)
    return [f.name for f in ds.frames(root.name)], None


def _cpp(binary: Path, server: str, root: Path) -> tuple[list[str] | None, str | None]:
    """(the frames the C++ client sent, None) or (None, its one `error:` line, less
    `error: ` and with its `image list` said `list`, as Python says it)."""
    done = subprocess.run([str(binary), "--server", server, "--timeout", "20", str(root)],
                          capture_output=True, text=True, timeout=60, check=False)
    if done.returncode == 0:
        assert done.stderr == ""
        lines = done.stdout.splitlines()
        assert all(re.fullmatch(r"# .*: not localized \(0 inliers\)", ln) for ln in lines)
        # names as `slamreloc localize` writes them (`line_name`: percent-encoded where needed)
        return [Path(unquote(ln[2:].split(": not localized")[0])).stem for ln in lines], None
    assert done.returncode == 2, (done.returncode, done.stdout, done.stderr)
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), done.stderr
    return None, lines[0].removeprefix("error: ").replace(": image list ", ": list ")


RULE = ": fields are separated by spaces or tabs only, lines end at a line feed (or CR LF)"
BLANK = "list holds a blank or line break other than a space, a tab or a line feed"
LONE_CR = "list holds a carriage return not followed by a line feed"
NBSP, EM_SPACE, NEL, LSEP = "\u00a0", "\u2003", "\u0085", "\u2028"

# (rgb.txt, the frames both read, or the message both give after `FOLDER/rgb.txt`)
VARIANTS = {
    "plain": (b"1.0 rgb/a.png\n2.0 rgb/b.png\n", ["a", "b"]),
    "no final line end": (b"1.0 rgb/a.png\n2.0 rgb/b.png", ["a", "b"]),
    "crlf": (b"1.0 rgb/a.png\r\n2.0 rgb/b.png\r\n", ["a", "b"]),
    "tabs and spaces": (b"  1.0\t \trgb/a.png \t\n\t2.0 rgb/b.png\n", ["a", "b"]),
    "comments, blank lines": (b"# color images\n\n \t\n#x\t y\n1.0 rgb/a.png\n \t# z\n"
                              b"3.0 rgb/c.png\r\n", ["a", "c"]),
    "bom": (b"\xef\xbb\xbf1.0 rgb/a.png\n2.0 rgb/b.png\n", ["a", "b"]),
    "nbsp between fields": (f"1.0{NBSP}rgb/a.png\n".encode(),
                            f":1: {BLANK} (U+00A0){RULE}"),
    "em space": (f"1.0 rgb/a.png\n2.0{EM_SPACE}rgb/b.png\n".encode(),
                 f":2: {BLANK} (U+2003){RULE}"),
    "unit separator": (b"1.0\x1frgb/a.png\n",
                       f":1: {BLANK} (U+001F){RULE}"),
    "old mac line ends": (b"1.0 rgb/a.png\r2.0 rgb/b.png\r",
                          f":1: {LONE_CR} (U+000D){RULE}"),
    "cr at the end": (b"1.0 rgb/a.png\n2.0 rgb/b.png\r",
                      f":2: {LONE_CR} (U+000D){RULE}"),
    "form feed": (b"1.0 rgb/a.png\x0c2.0 rgb/b.png\n",
                  f":1: {BLANK} (U+000C){RULE}"),
    "vertical tab": (b"1.0\x0brgb/a.png\n", f":1: {BLANK} (U+000B){RULE}"),
    "nel": (f"# a\n1.0 rgb/a.png{NEL}2.0 rgb/b.png\n".encode(),
            f":2: {BLANK} (U+0085){RULE}"),
    "line separator": (f"1.0 rgb/a.png{LSEP}2.0 rgb/b.png\n".encode(),
                       f":1: {BLANK} (U+2028){RULE}"),
    "paragraph separator": ("1.0 rgb/a.png\n\n\u20292.0 rgb/b.png\n".encode(),
                            f":3: {BLANK} (U+2029){RULE}"),
    "ideographic space in a comment": ("#\u3000x\n1.0 rgb/a.png\n".encode(),
                                       f":1: {BLANK} (U+3000){RULE}"),
    "latin-1": (b"1.0 rgb/\xe9.png\n", ": list is not UTF-8 text (byte 8)"),
    "overlong": (b"1.0 rgb/a.png\n2.0 rgb/\xc0\xafb.png\n", ": list is not UTF-8 text (byte 22)"),
    "surrogate": (b"1.0 rgb/\xed\xa0\x80.png\n", ": list is not UTF-8 text (byte 8)"),
    "beyond U+10FFFF": (b"1.0 rgb/\xf4\x90\x80\x80.png\n", ": list is not UTF-8 text (byte 8)"),
    "cut short at the end": (b"1.0 rgb/a.png\n\xe2\x82", ": list is not UTF-8 text (byte 14)"),
    "bom twice": (b"\xef\xbb\xbf\xef\xbb\xbf1.0 rgb/a.png\n",
                  ":1: timestamp"),  # a second one is not dropped: a field's first character
    "nul": (b"1.0 rgb/a.png\n2.0 rgb/\x00.png\n", ":2: list holds a NUL byte (byte 22); text "
            "files have none"),
    "three fields": (b"1.0 rgb/a.png x\n", ":1: expected 2 fields, got 3"),
}


@needs_cpp
@pytest.mark.parametrize("name", VARIANTS)
def test_python_and_cpp_read_rgb_txt_alike(client_binary, fake_server, tmp_path,
                                           name):
    content, expected = VARIANTS[name]
    root = _tum_folder(tmp_path / "tum", content)
    py, cpp = _python(root), _cpp(client_binary, fake_server, root)
    if isinstance(expected, list):
        assert py == cpp == (expected, None), (py, cpp)
    else:
        assert py[0] is None and cpp[0] is None, (py, cpp)
        assert py[1].startswith(f"{root / 'rgb.txt'}{expected}"), py[1]
        assert cpp[1].startswith(f"{root / 'rgb.txt'}{expected}"), cpp[1]
        if "timestamp" not in expected:  # the number rule's wording differs after its start
            assert py[1] == cpp[1]


def _refused_by_python(c: str) -> bool:
    try:
        plain_lines(f"1.0 rgb/a{c}.png\n", "rgb.txt", "list")
    except InputError:
        return True
    return False


# every character the list rule refuses (each blank or line break but a space, a tab, "\n" and
# the "\r" of a "\r\n"); the control characters that are no blank (NUL aside: no text file
# holds one), which the list takes and the frame name rule refuses; and printable characters
BLANKS = [chr(c) for c in range(0x110000) if chr(c).isspace() and chr(c) not in " \t\n"]
CONTROLS = [chr(c) for c in range(1, 0x110000)
            if unicodedata.category(chr(c)) == "Cc" and not chr(c).isspace()]
PRINTABLE = ["x", "#", "\u00e9", "\u3001", "\uff10", "\U0001f600", "%", "'", '"']


@needs_cpp
def test_the_two_readers_refuse_the_same_characters(client_binary, fake_server,
                                                    tmp_path):
    """Each blank or line break other than a space, a tab and "\\n" in a file name: refused by
    both by the list rule, with one message naming line 1. Each other control character:
    refused by both by the frame name rule (`frame_name_problem`; the C++ client names the
    line). A printable character: the frames are read by both."""
    assert len(BLANKS) == 26 and all(_refused_by_python(c) for c in BLANKS)
    assert len(CONTROLS) == 54 and not any(_refused_by_python(c) for c in CONTROLS)
    png = cv2.imencode(".png", np.zeros((240, 320, 3), np.uint8))[1].tobytes()
    for i, c in enumerate(BLANKS + CONTROLS + PRINTABLE):
        root = _tum_folder(tmp_path / f"t{i}", f"1.0 rgb/a{c}.png\n2.0 rgb/b.png\n".encode())
        if c not in BLANKS:
            (root / "rgb" / f"a{c}.png").write_bytes(png)
        py, cpp = _python(root), _cpp(client_binary, fake_server, root)
        if c in BLANKS:
            assert py[0] is None and py[1] == cpp[1], (hex(ord(c)), py, cpp)
            assert py[1].startswith(f"{root / 'rgb.txt'}:1: list holds "), py[1]
        elif c in CONTROLS:
            assert py[0] is None and py[1].startswith(f"{root}: frame name 'a"), py
            assert "control character" in py[1], py
            assert cpp[0] is None and cpp[1].startswith(f"{root / 'rgb.txt'}:1: frame name "
                                                        "'a\\x"), cpp
            assert "control character" in cpp[1] and c not in cpp[1], cpp
        else:
            assert py == cpp == ([f"a{c}", "b"], None), (py, cpp)


@needs_cpp
@pytest.mark.parametrize("stem,problem", [
    ("a\\b", None), ("a.b", None), ("...", None), ("a\\", "not a plain relative path"),
    ("a\\\\b", "not a plain relative path"), ("a\\.\\b", "not a plain relative path"),
    ("\\a", "not a plain relative path"), ("..", "not a path inside the dataset"),
    ("a\\..\\b", "not a path inside the dataset")])
def test_frame_names_follow_the_python_rule(client_binary, fake_server, tmp_path,
                                            stem, problem):
    """A TUM frame is named by its file's stem, by `frame_name_problem` (a backslash read as a
    slash): a name Python refuses, the C++ client refuses too, naming the line."""
    root = _tum_folder(tmp_path / "tum", f"1.0 rgb/{stem}.png\n2.0 rgb/a.png\n".encode())
    cv2.imwrite(str(root / "rgb" / f"{stem}.png"), np.zeros((240, 320, 3), np.uint8))
    py, cpp = _python(root), _cpp(client_binary, fake_server, root)
    if problem is None:
        assert py == cpp == ([stem, "a"], None), (py, cpp)
    else:
        assert py[0] is None and py[1].startswith(f"{root}: frame name ") and problem in py[1]
        assert cpp[0] is None and cpp[1].startswith(f"{root / 'rgb.txt'}:1: frame name ")
        assert problem in cpp[1], cpp


@pytest.mark.parametrize("listing", ["depth.txt", "groundtruth.txt"])
@pytest.mark.parametrize("odd", [NBSP, "\x0b", "\x0c", "\r", NEL, LSEP])
def test_depth_and_ground_truth_follow_the_same_rule(tmp_path, listing, odd):
    """One rule for TUM's three lists: depth.txt (read by the rgb.txt reader) and
    groundtruth.txt (the TUM trajectory reader) refuse what rgb.txt refuses, naming the line."""
    root = _tum_folder(tmp_path, b"1.0 rgb/a.png\n")
    depth = np.full((240, 320), 5000, np.uint16)
    cv2.imwrite(str(root / "depth.png"), depth)
    rows = {"depth.txt": ["1.0", "depth.png"],
            "groundtruth.txt": ["1.0", "0", "0", "0", "0", "0", "0", "1"]}[listing]
    (root / listing).write_text("# " + listing + "\n" + " ".join(rows) + "\n", newline="")
    assert _python(root) == (["a"], None)
    (root / listing).write_text("# " + listing + "\n" + rows[0] + odd + " ".join(rows[1:])
                                + "\n", newline="")
    frames, message = _python(root)
    assert frames is None and message.startswith(f"{root / listing}:2: "), message
    assert "holds a" in message and RULE in message, message


def test_tum_trajectories_take_crlf_and_a_bom(tmp_path):
    """What the rule takes: "\\r\\n" line ends, a leading byte-order mark, tabs."""
    path = tmp_path / "t.txt"
    path.write_bytes(b"\xef\xbb\xbf# t\r\n1.0\t0 0 0 0 0 0 1\r\n2.0 0 0 0  0\t0 0 1\r\n")
    assert [stamp for stamp, _ in read_tum_trajectory(path)] == ["1.0", "2.0"]


OPTIONS = {"--server": ("127.0.0.1:1", "127.0.0.1:2"), "--map": ("a", "b"),
           "--token": ("a" * 20, "b" * 20), "--tls-ca": ("a.pem", "b.pem"),
           "--camera": ("PINHOLE 320 240 262.5 262.5 159.5 119.5",
                        "PINHOLE 320 240 100 100 159.5 119.5"),
           "--timeout": ("1", "2")}


@needs_cpp
@pytest.mark.parametrize("form", ["two", "equals", "same value", "bad first value"])
@pytest.mark.parametrize("option", OPTIONS)
def test_an_option_given_twice_is_refused(client_binary, tmp_path, option, form):
    """E5: the C++ client kept the last of an option given twice; it now refuses it as the
    Python CLI does, before reading any value (`--server=X` and `--server X` alike)."""
    first, second = OPTIONS[option]
    given = {"two": [option, first, option, second],
             "equals": [f"{option}={first}", option, second],
             "same value": [option, first, f"{option}={first}"],
             "bad first value": [option, "", option, second]}[form]
    server = [] if option == "--server" else ["--server", "127.0.0.1:1"]
    done = subprocess.run([str(client_binary), *server, *given, str(tmp_path / "no-such")],
                          capture_output=True, text=True, timeout=60, check=False)
    assert (done.returncode, done.stdout, done.stderr) == (
        2, "", f"error: {option} is given twice: give it once\n")


@needs_cpp
def test_the_repeat_message_is_the_python_clis(client_binary, tmp_path):
    """The same line as `slamreloc localize ... --camera A --camera B`."""
    camera_a, camera_b = OPTIONS["--camera"]
    status, _, err = run_cli_output(["localize", str(tmp_path / "map"), str(tmp_path / "x.png"),
                                     "--camera", camera_a, "--camera", camera_b])
    done = subprocess.run([str(client_binary), "--server", "127.0.0.1:1", "--camera", camera_a,
                           "--camera", camera_b, str(tmp_path)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert status == done.returncode == 2
    assert err.strip().splitlines()[-1] == done.stderr.strip() == \
        "error: --camera is given twice: give it once"


@needs_cpp
def test_options_given_once_are_still_taken(client_binary, fake_server, tmp_path):
    """Each option once (a value that looks like an option name included) is as before."""
    root = _tum_folder(tmp_path / "tum", b"1.0 rgb/a.png\n2.0 rgb/b.png\n")
    done = subprocess.run([str(client_binary), "--server", fake_server, "--map=--map",
                           "--timeout", "30", "--camera", OPTIONS["--camera"][0], str(root)],
                          capture_output=True, text=True, timeout=60, check=False,
                          env={"PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["# a.png: not localized (0 inliers)",
                                        "# b.png: not localized (0 inliers)"]


def test_the_printable_table_is_pythons():
    """clients/cpp/nonprintable.inc, the C++ client's table of characters Python's
    str.isprintable() refuses, is what its generator writes from this Python's Unicode data:
    the client's name rules and the server's refuse the same characters."""
    root = Path(__file__).resolve().parents[1] / "clients" / "cpp"
    done = subprocess.run(["python", str(root / "nonprintable.py")], capture_output=True,
                          text=True, timeout=120, check=True)
    assert (root / "nonprintable.inc").read_text() == done.stdout, (
        "clients/cpp/nonprintable.inc is stale: run python clients/cpp/nonprintable.py > "
        "clients/cpp/nonprintable.inc")


# characters that are no control character and no blank, and still not printable to Python:
# format (soft hyphen, zero-width space, BOM inside a name, a tag), private-use, unassigned
NOT_PRINTABLE = ["\u00ad", "\u200b", "\u2066", "\ufeff", "\U000e0001", "\ue000",
                 "\U000f0000", "\U0010fffd", "\u0378", "\U0003fffd", "\ufdd0"]


@needs_cpp
def test_format_private_and_unassigned_characters_are_refused_alike(
        client_binary, fake_server, tmp_path):
    """A frame name or a map name holding a character that is printable to neither side's
    rule: the C++ client refuses it before sending anything, as Python does (it was left to
    the server for format, private-use and unassigned characters)."""
    assert not any(c.isprintable() or c.isspace() or unicodedata.category(c) == "Cc"
                   for c in NOT_PRINTABLE)
    for i, c in enumerate(NOT_PRINTABLE):
        root = _tum_folder(tmp_path / f"t{i}", f"1.0 rgb/a{c}.png\n2.0 rgb/b.png\n".encode())
        cv2.imwrite(str(root / "rgb" / f"a{c}.png"), np.zeros((240, 320, 3), np.uint8))
        py, cpp = _python(root), _cpp(client_binary, fake_server, root)
        assert py[0] is None and "control character" in py[1], (hex(ord(c)), py)
        assert cpp[0] is None and cpp[1].startswith(f"{root / 'rgb.txt'}:1: frame name "), cpp
        assert "control character" in cpp[1], (hex(ord(c)), cpp)
        assert map_name_problem(f"m{c}") is not None
        done = subprocess.run([str(client_binary), "--server", fake_server, "--map", f"m{c}",
                               str(tmp_path / f"t{i}")], capture_output=True, text=True,
                              timeout=60, check=False)
        assert done.returncode == 2 and done.stdout == "", (hex(ord(c)), done)
        assert done.stderr.startswith("error: --map ") and "printable" in done.stderr, done
    for c in ("\u00e9", "\U0001f600", "\u3001"):  # printable: taken by both
        root = _tum_folder(tmp_path / f"ok{ord(c)}", f"1.0 rgb/{c}.png\n".encode())
        cv2.imwrite(str(root / "rgb" / f"{c}.png"), np.zeros((240, 320, 3), np.uint8))
        assert _python(root) == _cpp(client_binary, fake_server, root) == ([c], None)
