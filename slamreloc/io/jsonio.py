"""Reading JSON from untrusted files: bounded size and nesting, finite numbers only, and typed
access to fields whose errors name the file and the field (`report.json: events[3].frame must
be a whole number, got "abc"`).

`read_json` is the one JSON reader of the package (map metadata, scene descriptions, reports);
`Json` wraps a parsed value for typed reading.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from collections.abc import Callable
from typing import Any

import numpy as np

from slamreloc.errors import InputError
from slamreloc.io.fileio import read_bytes
from slamreloc.io.limits import bytes_text, limits, over_limit


def _refuse_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def _depth(value: Any, limit: int) -> int:
    """Nesting depth of arrays and objects (iterative: no recursion to exhaust)."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, (list, dict)):
            deepest = max(deepest, d)
            if deepest > limit:
                return deepest
            stack.extend((c, d + 1) for c in (v.values() if isinstance(v, dict) else v))
    return deepest


def _bounded_int(text: str) -> int:
    """A JSON integer that fits 64 bits (a 10^400 literal would end in OverflowError later)."""
    digits = len(text.lstrip("-"))
    if digits > 19 or not -(2 ** 63) <= int(text) < 2 ** 63:
        raise ValueError(f"an integer of {digits} digits, beyond 64 bits" if digits > 19
                         else f"integer {text} beyond 64 bits")
    return int(text)


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict:
    """A JSON object whose keys are all different (a key given twice would keep only its last
    value without a word: which one the writer meant is not for the reader to guess)."""
    value = dict(pairs)
    if len(value) != len(pairs):
        seen: set[str] = set()
        twice = next(k for k, _ in pairs if k in seen or seen.add(k))
        raise ValueError(f"key {json.dumps(twice)[:40]} appears twice in one object")
    return value


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text[:24]} out of range")
    return value


def parse_json(data: bytes | str, source, what: str = "JSON") -> Any:
    """A parsed JSON value: InputError (naming `source`) on invalid JSON, NaN / Infinity, a key
    given twice in one object, a number literal that overflows (an integer beyond 64 bits, a
    float that reads as infinite), nesting deeper than `max_json_depth` (at most 500: the
    parser itself stops at Python's recursion limit, ~1000 levels, with a RecursionError,
    refused the same way)."""
    lim = limits()
    if len(data) > lim.max_json_bytes:
        raise InputError(f"{source}: {what} of " + over_limit("max_json_bytes",
                                                              bytes_text(len(data))))
    try:
        value = json.loads(data, parse_constant=_refuse_constant, parse_int=_bounded_int,
                           parse_float=_finite_float, object_pairs_hook=_unique_keys)
    except RecursionError:  # deeper than any max_json_depth may be (LIMIT_MAXIMA)
        raise InputError(f"{source}: {what} nested more than {lim.max_json_depth} levels "
                         "deep, " + over_limit("max_json_depth")) from None
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError, NaN / Infinity
        raise InputError(f"{source}: not valid {what} ({' '.join(str(err).split())[:200]})"
                         ) from None
    if _depth(value, lim.max_json_depth) > lim.max_json_depth:
        raise InputError(f"{source}: {what} nested more than {lim.max_json_depth} levels "
                         "deep, " + over_limit("max_json_depth"))
    return value


def read_json(path: str | Path, what: str = "JSON") -> dict:
    """The JSON object in a file (bounded by `max_json_bytes` and `max_json_depth`)."""
    path = Path(path)
    value = parse_json(read_bytes(path, what, "max_json_bytes"), path, what)
    if not isinstance(value, dict):
        raise InputError(f"{path}: {what} must be a JSON object, got {_kind(value)}")
    return value


def _kind(value: Any) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "true/false",
            type(None): "null"}.get(type(value), "a number")


def _short(value: Any) -> str:
    text = json.dumps(value) if isinstance(value, (str, int, float, bool, type(None))) else \
        _kind(value)
    return text if len(text) <= 40 else text[:37] + "..."


class Json:
    """A parsed JSON value and where it came from (`source`: the file; `where`: the field path),
    read through typed accessors that raise InputError naming both."""

    def __init__(self, value: Any, source, where: str = "") -> None:
        self.value, self.source, self.where = value, source, where

    def _fail(self, problem: str, key: str | int | None = None) -> InputError:
        where = self._path(key)
        return InputError(f"{self.source}: {where + ' ' if where else ''}{problem}")

    def _path(self, key: str | int | None) -> str:
        if key is None:
            return self.where
        return f"{self.where}[{key}]" if isinstance(key, int) else (
            f"{self.where}.{key}" if self.where else str(key))

    def has(self, key: str) -> bool:
        return isinstance(self.value, dict) and self.value.get(key) is not None

    def child(self, key: str | int) -> Json:
        container = self.value
        if isinstance(key, str) and not isinstance(container, dict):
            raise self._fail(f"must be an object, got {_kind(container)}")
        try:
            return Json(container[key], self.source, self._path(key))
        except (KeyError, IndexError, TypeError):
            raise self._fail("is missing", key) from None

    def get(self, key: str) -> Json | None:
        """The field, or None where it is absent or null."""
        if not isinstance(self.value, dict):
            raise self._fail(f"must be an object, got {_kind(self.value)}")
        return None if self.value.get(key) is None else self.child(key)

    # --- typed values ---------------------------------------------------------------------
    def obj(self) -> dict:
        if not isinstance(self.value, dict):
            raise self._fail(f"must be an object, got {_kind(self.value)}")
        return self.value

    def items(self) -> list[tuple[str, Json]]:
        return [(k, self.child(k)) for k in self.obj()]

    def list(self) -> list[Json]:
        if not isinstance(self.value, list):
            raise self._fail(f"must be a list, got {_kind(self.value)}")
        return [self.child(i) for i in range(len(self.value))]

    def str(self) -> str:
        if not isinstance(self.value, str):
            raise self._fail(f"must be a string, got {_short(self.value)}")
        return self.value

    def bool(self) -> bool:
        if not isinstance(self.value, bool):
            raise self._fail(f"must be true or false, got {_short(self.value)}")
        return self.value

    def number(self) -> float:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self._fail(f"must be a finite number, got {_short(v)}")
        return float(v)

    def int(self) -> int:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, int):
            raise self._fail(f"must be a whole number, got {_short(v)}")
        return v

    def array(self, shape: tuple[int | None, ...]) -> np.ndarray:
        """A float64 array of finite numbers with `shape` (only the first size may be None:
        any length)."""
        def ok(v, dims) -> bool:
            if not dims:
                return isinstance(v, (int, float)) and not isinstance(v, bool) \
                    and math.isfinite(v)
            return isinstance(v, list) and (dims[0] is None or len(v) == dims[0]) and \
                all(ok(c, dims[1:]) for c in v)

        if not ok(self.value, shape):
            want = "x".join("N" if s is None else str(s) for s in shape)
            raise self._fail(f"must be a {want} array of finite numbers")
        return np.array(self.value, dtype=np.float64).reshape(
            (len(self.value), *shape[1:]) if shape else ())

    # --- optional fields --------------------------------------------------------------------
    def opt(self, key: str, read: Callable[[Json], Any]) -> Any:
        """`read(field)` (e.g. `Json.number`) of the field `key`, or None where it is absent or
        null."""
        field = self.get(key)
        return None if field is None else read(field)


def report_kind(data: dict) -> str:
    """The slamreloc command a REPORT.json came from, by the keys each writes: "evaluate",
    "pseudo-label", "slam", or "other" (no report of slamreloc's). Any one of a kind's keys
    decides (the viewer shows what such a file holds); `written_report_kind` asks for all."""
    if "per_query" in data or "n_queries" in data:
        return "evaluate"
    if "n_pseudo_labels" in data or "n_new_points" in data:
        return "pseudo-label"
    if any(k in data for k in ("ate_rmse_m", "n_kidnaps", "events", "graph_edges")):
        return "slam"
    return "other"


# the fields every report of a kind holds (what each command always writes)
REPORT_KEYS = {
    "evaluate": ("method", "n_queries", "n_localized", "recall", "per_query"),
    "pseudo-label": ("n_frames", "n_frames_registered", "n_pseudo_labels", "n_new_points"),
    "slam": ("n_frames", "odometry", "ate_rmse_m", "events"),
}


def written_report_kind(data: dict) -> str:
    """`report_kind`, where the file holds every field that command always writes
    (`REPORT_KEYS`), else "other": what an output may replace (a user's notes holding an
    `n_queries` are no report of slamreloc's)."""
    kind = report_kind(data)
    return kind if kind != "other" and all(k in data for k in REPORT_KEYS[kind]) else "other"
