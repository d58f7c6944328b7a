"""Values by the names of their fields, one rule per kind for every JSON record slamreloc
writes and reads back (a command's report, a map's `slamreloc_map.json`): counts are whole
numbers >= 0, distances, errors and durations >= 0, angles in [0, 180], shares in [0, 1], and
every number a finite float or an integer within int64."""

from __future__ import annotations

import math
import re
from collections.abc import Callable

from slamreloc.errors import InputError

MAX_INT = 2 ** 63 - 1  # counts and indices: int64 (numpy reads them as such)


# Fields by their names, as every slamreloc report and map record writes them: `n_*` / `num_*`
# (and `parameters`) are counts, `*_m` / `*_cm` / `*_deg` / `*_px` / `*_s` / `*_ms` distances,
# errors, angles and durations, never negative, angles (`*_deg`) at most 180; `recall`,
# `*_fraction` and `*precision_*` shares in [0, 1] (null: not measured; an object of such, as
# `timings_s`, holds them per stage or threshold); byte sizes, kidnap settings and frame counts
# are counts, rates (`*_fps`), ratios (`*_share`), lengths and per-call times measures, and a few
# named flags true or false. A report's own `poses` maps frame names, not fields.
COUNT = re.compile(r"(n|num)_\w+|parameters|\w+_bytes|kidnap_(every|skip)|frames_to_\w+")
MEASURE = re.compile(r"\w+_(m|cm|deg|px|s|ms|fps|length|share)|\w+_ms_per_\w+|median_frames_\w+")
FRACTION = re.compile(r"recall|\w+_fraction|\w*precision_\w+")  # shares: [0, 1]
FLAG = re.compile(r"guided_refinement|truth_aligned_\w+|noise_anneal|learned_live|accepted")
KINDS = ("count", "measure", "angle", "fraction", "flag")  # the rules a name gives


def check_values(value, source, names: tuple[str, ...] = (),
                 name_problem: Callable[[str], str | None] | None = None) -> None:
    """InputError naming `source` and the field of the first value that breaks the report
    rules: a number that is not a finite float or an integer within +-MAX_INT, a count
    (`COUNT`) that is not a whole number >= 0, a measure (`MEASURE`) that is not a number >= 0,
    or a key of a top-level object in `names` (a report's `poses`) for which `name_problem`
    (`types.frame_name_problem`) names a problem. Iterative: any nesting."""
    stack = [(value, "", "top")]
    while stack:
        v, where, rule = stack.pop()
        if isinstance(v, dict):
            for k, c in v.items():
                field = f"{where}.{k}" if where else str(k)
                if rule == "names":
                    problem = name_problem(k) if name_problem else None
                    if problem:
                        raise InputError(f"{source}: {where}: the frame name {k[:80]!r} "
                                         f"{problem}")
                    stack.append((c, field, None))
                else:
                    stack.append((c, field, _rule(k, rule, names)))
            continue
        if isinstance(v, list):
            # a list under a named kind holds values of that kind
            inner = rule if rule in KINDS else None
            stack.extend((c, f"{where}[{i}]", inner) for i, c in enumerate(v))
            continue
        _check_scalar(v, where, rule, source)


def _rule(key: str, parent: str | None, names: tuple[str, ...]) -> str | None:
    """The rule for the value under `key` (inside an object checked by `parent`'s rule;
    "top": the report itself): its own name's kind, else its object's (an object under a
    named kind holds values of that kind: `timings_s` per stage, `recall` per threshold)."""
    if key in names and parent == "top":  # a report's own `poses` (not `dataset.poses`)
        return "names"
    if COUNT.fullmatch(key):
        return "count"
    if FRACTION.fullmatch(key):
        return "fraction"
    if MEASURE.fullmatch(key):
        return "angle" if key.endswith("_deg") else "measure"
    if FLAG.fullmatch(key):
        return "flag"
    return parent if parent in KINDS else None


def _check_scalar(v, where: str, rule: str | None, source) -> None:
    field = where or "the value"
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) > MAX_INT:
        raise InputError(f"{source}: {field}: an integer of {len(str(abs(v)))} digits, out of "
                         f"range (at most {MAX_INT})")
    if isinstance(v, float) and not math.isfinite(v):
        raise InputError(f"{source}: {field}: a number beyond the range of a float (read as "
                         "infinite)")
    if rule is None or v is None:
        return
    number = isinstance(v, (int, float)) and not isinstance(v, bool)
    if rule == "count" and not (number and isinstance(v, int) and v >= 0):
        raise InputError(f"{source}: {field} is a count, a whole number >= 0; got {_short(v)}")
    if rule == "measure" and not (number and v >= 0):
        raise InputError(f"{source}: {field} is a measure (distance, angle or time), a number "
                         f">= 0; got {_short(v)}")
    if rule == "angle" and not (number and 0 <= v <= 180):
        raise InputError(f"{source}: {field} is an angle between two directions, in [0, 180] "
                         f"degrees; got {_short(v)}")
    if rule == "fraction" and not (number and 0 <= v <= 1):
        raise InputError(f"{source}: {field} is a share, a number in [0, 1]; got {_short(v)}")
    if rule == "flag" and not isinstance(v, bool):
        raise InputError(f"{source}: {field} is true or false; got {_short(v)}")
    if rule == "names":
        raise InputError(f"{source}: {field} must be an object of frame names, got {_short(v)}")


def _short(v) -> str:
    text = repr(v)
    return text if len(text) <= 40 else text[:37] + "..."
