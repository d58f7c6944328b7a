"""Fuzzing helpers: hypothesis strategies that damage valid files, a hang guard, case counters.

The counters (one per executed case) are checked against the fuzzing budget by
tests/test_fuzz_inputs.py's last test, printed at the end of the pytest run (conftest's terminal
summary) and written to `<pytest basetemp>/fuzz_counts.json`.
"""

from __future__ import annotations

import json
import math
import signal
from collections import Counter
from contextlib import contextmanager

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

COUNTS: Counter = Counter()  # (format, outcome) -> cases tried
KILL_REPORTS: list[dict] = []  # kill -9 harness reports (tests/test_crash_safety.py)

# fixed and derandomized: CI runs the same cases every time; no example database on disk
FUZZ = dict(deadline=None, derandomize=True, database=None, print_blob=True,
            suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                   HealthCheck.function_scoped_fixture])


def fuzz_settings(n: int) -> settings:
    return settings(max_examples=n, **FUZZ)


class Hang(Exception):
    """A loader took longer than the hang limit."""


@contextmanager
def no_hang(seconds: float = 20.0):
    """Fail (raise Hang) if the block runs longer than `seconds` (Python-level code)."""
    def alarm(signum, frame):
        raise Hang(f"no result after {seconds} s")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def run_cli(argv: list[str], hang_s: float = 60.0) -> tuple[int, str]:
    """`slamreloc ARGV` in this process: (exit status, stderr)."""
    code, _, err = run_cli_output(argv, hang_s)
    return code, err


def run_cli_output(argv: list[str], hang_s: float = 60.0) -> tuple[int, str, str]:
    """`slamreloc ARGV` in this process: (exit status, stdout, stderr). The input bounds a
    `--limit` sets are put back after it."""
    import io
    import sys
    from contextlib import redirect_stderr, redirect_stdout

    from slamreloc import cli
    from slamreloc.io import limits

    err, out = io.StringIO(), io.StringIO()
    old = sys.argv
    old_limits = limits._current  # a `--limit` holds for its own command, as in its process
    sys.argv = ["slamreloc", *argv]
    try:
        with redirect_stderr(err), redirect_stdout(out), no_hang(hang_s):
            try:
                cli.main()
                code = 0
            except SystemExit as exit_:
                code = exit_.code if isinstance(exit_.code, int) else 1
    finally:
        sys.argv = old
        limits._current = old_limits
    return code, out.getvalue(), err.getvalue()


def total_cases() -> int:
    return sum(COUNTS.values())


def summary() -> dict:
    by_format: dict[str, dict[str, int]] = {}
    for (fmt, outcome), n in sorted(COUNTS.items()):
        by_format.setdefault(fmt, {})[outcome] = n
    return {"total": total_cases(), "by_format": by_format}


# --- damaged bytes -------------------------------------------------------------------------

@st.composite
def damaged_bytes(draw, data: bytes) -> bytes:
    """Truncated, emptied, bit-flipped, overwritten, spliced or replaced bytes of `data`."""
    n = len(data)
    kind = draw(st.sampled_from(["truncate", "truncate", "empty", "flip", "flip", "flip_head",
                                 "overwrite", "insert", "delete", "append", "random"]))
    if n == 0 or kind == "random":
        return draw(st.binary(max_size=256))
    if kind == "empty":
        return b""
    if kind == "truncate":
        return data[:draw(st.integers(0, n - 1))]
    if kind in ("flip", "flip_head"):
        hi = min(n, 128) - 1 if kind == "flip_head" else n - 1
        out = bytearray(data)
        for pos, bit in draw(st.lists(st.tuples(st.integers(0, hi), st.integers(0, 7)),
                                      min_size=1, max_size=12)):
            out[pos] ^= 1 << bit
        return bytes(out)
    pos = draw(st.integers(0, n - 1))
    if kind == "overwrite":
        chunk = draw(st.binary(min_size=1, max_size=64))
        return data[:pos] + chunk + data[pos + len(chunk):]
    if kind == "insert":
        return data[:pos] + draw(st.binary(min_size=1, max_size=64)) + data[pos:]
    if kind == "delete":
        return data[:pos] + data[pos + draw(st.integers(1, 64)):]
    return data + draw(st.binary(min_size=1, max_size=64))  # append


# --- damaged text ----------------------------------------------------------------------------

GARBAGE = ["nan", "NaN", "-nan", "inf", "-inf", "Infinity", "1e999", "-1e999", "1e308",
           "-1.7e308", "1e-320", "0", "-0", "abc", "1,5", "0x10", "\u0661", "\x00", "--1", "1e",
           "", "+", "9" * 400, "\u00e9", "#", "1.0.0", "sequence", "sequence99", "sequence-1",
           "sequence000001", "seq-01", "rgb/none.png", "../x.png", "/", "\t"]

tokens = st.one_of(st.sampled_from(GARBAGE),
                   st.floats(allow_nan=True, allow_infinity=True).map(repr),
                   st.integers(-(2 ** 70), 2 ** 70).map(str),
                   st.text(max_size=12))


@st.composite
def damaged_text(draw, text: str) -> bytes:
    """A text file with a token or line replaced, removed, repeated or scaled (non-rigid
    poses), garbage lines, or damaged bytes."""
    lines = text.splitlines()
    kind = draw(st.sampled_from(["token", "token", "token", "scale", "del_token", "add_token",
                                 "del_line", "dup_line", "add_line", "swap_lines", "random",
                                 "bytes"]))
    if kind == "bytes" or not lines:
        return draw(damaged_bytes(text.encode()))
    if kind == "random":
        return draw(st.text(max_size=300)).encode("utf-8", "surrogatepass")
    i = draw(st.integers(0, len(lines) - 1))
    words = lines[i].split()
    if kind in ("token", "scale", "del_token", "add_token") and words:
        j = draw(st.integers(0, len(words) - 1))
        if kind == "token":
            words[j] = draw(tokens)
        elif kind == "scale":
            try:
                value = float(words[j])
            except ValueError:
                value = 1.0
            factor = draw(st.sampled_from([0.0, -1.0, 1.01, 2.0, 1e-9, 1e10, 1e300]))
            words[j] = repr(value * factor if math.isfinite(value * factor) else value)
        elif kind == "del_token":
            del words[j]
        else:
            words.insert(j, draw(tokens))
        lines[i] = " ".join(words)
    elif kind == "del_line":
        del lines[i]
    elif kind == "dup_line":
        lines.insert(i, lines[i])
    elif kind == "add_line":
        lines.insert(i, " ".join(draw(st.lists(tokens, max_size=9))))
    elif kind == "swap_lines":
        k = draw(st.integers(0, len(lines) - 1))
        lines[i], lines[k] = lines[k], lines[i]
    return ("\n".join(lines) + "\n").encode("utf-8", "surrogatepass")


# --- damaged JSON ----------------------------------------------------------------------------

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2 ** 70), 2 ** 70)
    | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                 max_size=3),
    max_leaves=6)


def _paths(doc, prefix=()):
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:4]):
            yield from _paths(v, prefix + (i,))


@st.composite
def damaged_json(draw, doc) -> bytes:
    """A JSON document with a key removed, a value of the wrong type or range, a renamed key,
    another document entirely, or damaged bytes."""
    kind = draw(st.sampled_from(["replace", "replace", "replace", "delete", "delete", "rename",
                                 "number", "whole", "bytes"]))
    text = json.dumps(doc)
    if kind == "bytes":
        return draw(damaged_bytes(text.encode()))
    if kind == "whole":
        return json.dumps(draw(json_values)).encode()
    doc = json.loads(text)  # a private copy
    paths = [p for p in _paths(doc) if p]
    path = draw(st.sampled_from(paths))
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    key = path[-1]
    if kind == "delete":
        del parent[key]
    elif kind == "rename" and isinstance(parent, dict):
        parent[key + draw(st.sampled_from(["_", "X", " "]))] = parent.pop(key)
    elif kind == "number":
        parent[key] = draw(st.sampled_from([0, -1, 1.5, 2 ** 31, 2 ** 63, 10 ** 30, -1e308, 1e-300,
                                            float("nan"), float("inf"), True, "1", None]))
    else:
        parent[key] = draw(json_values)
    return json.dumps(doc).encode()
