"""Bounds on untrusted input, checked before anything is allocated for it.

Every reader takes its bound from here, so one setting covers the CLI, the Python API and a
service: the image decoder checks `max_image_pixels` against the header before it decodes, a
feature extractor checks the pixels it will work on, JSON readers check size and nesting depth.

Raise a bound with the CLI's global option (`slamreloc --limit max_image_pixels=50000000
localize ...`), the environment (`SLAMRELOC_MAX_IMAGE_PIXELS=50000000`), or `set_limits(...)`
in Python: a whole number in ASCII digits (`slamreloc.io.numbers`), each bound given once. An
environment variable named SLAMRELOC_ (in any case) that is neither a bound's nor one of
`KNOWN_VARIABLES`, or spelt like one but for case and punctuation, is refused, never ignored
(`environment_problem`). `slamreloc serve --engine ray` hands the driver's bounds to every map
replica (`use_limits`). The defaults keep every command under ~2 GB of memory on any input
(BENCHMARKS.md, "Input bounds"); docs/formats.md lists them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields, replace

from slamreloc.errors import InputError
from slamreloc.io.numbers import WHOLE_WORDS, number_problem

ENV_PREFIX = "SLAMRELOC_"


@dataclass(frozen=True)
class InputLimits:
    """Bounds on one input. Pixels count width x height (channels aside); bytes are file sizes
    on disk or on the wire."""

    max_image_pixels: int = 1 << 24  # 16.8 MP (4096 x 4096): decoded and worked-on images
    min_image_side: int = 16  # pixels: smaller images cannot hold a feature
    max_image_bytes: int = 256 << 20  # an encoded image file
    max_feature_bytes: int = 3 << 29  # 1.5 GiB: a feature extractor's working memory
    max_jpeg_scans: int = 256  # progressive JPEG: decode time grows with the scan count
    max_json_bytes: int = 16 << 20  # a report, a map's metadata, scene.json
    max_json_depth: int = 64  # nesting of JSON arrays and objects
    max_text_bytes: int = 1 << 30  # trajectories, COLMAP text models, split lists

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise InputError(f"limit {f.name} must be a positive integer, got {value!r}")


BOUND_VARIABLES = {ENV_PREFIX + f.name.upper(): f.name for f in fields(InputLimits)}
# Every other SLAMRELOC_ variable the project reads, in this one place (tests/test_round28_limits.py
# finds each name the code reads and requires it here): any other name that starts with
# SLAMRELOC_ in any case, or that is spelt like one of these but for case and punctuation, is
# refused where the bounds are read (`check_environment`), never ignored.
KNOWN_VARIABLES = {
    "SLAMRELOC_TOKEN": "the service's token (slamreloc.service.TOKEN_ENV; the C++ client)",
    "SLAMRELOC_TEST_CRASH_AT": "test hook: save_map kills itself at this step (map.write)",
    "SLAMRELOC_NO_RENAME_EXCHANGE": "test hook: the two-rename fallback (io.outputs)",
    "SLAMRELOC_DOCS_SLOW": "test suite: run the docs' slow blocks (tests/test_docs.py)",
    "SLAMRELOC_DOCS_REALDATA": "test suite: run the docs' real-data blocks (tests/test_docs.py)",
    "SLAMRELOC_FUZZ_SCALE": "test suite: scale of the fuzz runs (tests/test_fuzz_inputs.py)",
    "SLAMRELOC_KILLS": "test suite: kills of the kill -9 harness (tests/test_crash_safety.py)",
}


def _squeezed(name: str) -> str:
    """A name without case or punctuation (`SLAMRELOC_Max-Image_Pixels` ->
    `slamrelocmaximagepixels`): names alike in it are one name misspelt."""
    return "".join(c for c in name.lower() if c.isascii() and c.isalnum())


_LOOKALIKES = {_squeezed(n): n for n in (*BOUND_VARIABLES, *KNOWN_VARIABLES)}


def environment_problem(name: str) -> str | None:
    """Why the environment variable `name` is refused, or None. Taken: the bounds'
    SLAMRELOC_<NAME> (NAME in capitals, `BOUND_VARIABLES`), `KNOWN_VARIABLES`, and other
    programs' names. Refused, as a misspelling the user believes holds: any other name that
    starts with SLAMRELOC_ in any case; any name spelt like a bound's or a known variable's but
    for case and punctuation (`SLAMRELOC_max_image_pixels`, a bound's name short of an
    underscore, `SLAMRELOCTOKEN`); and a name that starts with SLAM (in any case, punctuation
    aside) a letter or two off one (difflib's ratio of the two `_squeezed` names at least 0.85:
    `SLAMRELCO_MAX_IMAGE_PIXELS`, `SLAM_MAX_IMAGE_PIXELS`). The problem says which bound or
    variable the name resembles, where one is near."""
    from difflib import get_close_matches

    if name in BOUND_VARIABLES or name in KNOWN_VARIABLES:
        return None
    squeezed = _squeezed(name)
    ours = name.upper().startswith(ENV_PREFIX)
    twin = _LOOKALIKES.get(squeezed)
    if twin is None and (ours or squeezed.startswith("slam")):
        near = get_close_matches(squeezed, _LOOKALIKES, n=1, cutoff=0.85)
        twin = _LOOKALIKES[near[0]] if near else None
    if twin is None and not ours:
        return None
    rest = squeezed[len("slamreloc"):]
    bound_like = twin in BOUND_VARIABLES or rest.startswith(("max", "min"))
    what = "names no bound" if bound_like else "names no slamreloc setting"
    if twin in BOUND_VARIABLES:
        hint = (f"it resembles the bound {BOUND_VARIABLES[twin]}, whose variable is exactly "
                f"{twin}")
    elif twin is not None:
        hint = f"it resembles {twin}, a name read exactly as spelt"
    elif bound_like:
        hint = f"the bounds are {', '.join(sorted(BOUND_VARIABLES))}"
    else:
        hint = (f"the settings are the bounds' SLAMRELOC_<NAME> (docs/formats.md, 'Bounds') "
                f"and {', '.join(sorted(KNOWN_VARIABLES))}")
    return f"environment variable {name[:80]} {what}: {hint}"


def check_environment() -> None:
    """InputError (one line naming the variable) for the first environment variable, by name,
    that `environment_problem` refuses; the CLI checks before every command."""
    for name in sorted(os.environ):
        problem = environment_problem(name)
        if problem:
            raise InputError(problem)


def _from_environment() -> InputLimits:
    check_environment()  # a misspelt bound would be ignored: the user believes it holds
    overrides = {}
    for name, bound in BOUND_VARIABLES.items():
        text = os.environ.get(name)
        if text is None:
            continue
        overrides[bound] = whole_limit(text, f"environment variable {name}", bound)
    return InputLimits(**overrides)


# bounds that something else caps below MAX_LIMIT: (the largest value, why)
LIMIT_MAXIMA = {"max_json_depth": (500, "the JSON parser itself stops near Python's recursion "
                                        "limit, about 1000 levels")}


def whole_limit(text: str, source: str, name: str | None = None) -> int:
    """A bound's value as text (`--limit`, an environment variable): a positive whole number
    by the project's number rule for whole numbers (`slamreloc.io.numbers`: ASCII digits; no
    exponent, fraction, separator or blank), at most MAX_LIMIT (and LIMIT_MAXIMA's value for
    the bound `name`); InputError naming `source`."""
    problem = number_problem(text, integer=True)
    if problem:
        raise InputError(f"{source}: {text[:40]!r} is {problem} ({WHOLE_WORDS}; a bound "
                         "is a count of pixels, bytes, ...)")
    value = int(text)
    if value <= 0:
        raise InputError(f"{source}: must be a positive whole number, got {text[:40]}")
    if value > MAX_LIMIT:  # a byte count a read or an allocation can still be asked for
        raise InputError(f"{source}: at most {MAX_LIMIT} (2**48: no input of that size can be "
                         f"read here), got {text[:40]}")
    if name in LIMIT_MAXIMA and value > LIMIT_MAXIMA[name][0]:
        top, why = LIMIT_MAXIMA[name]
        raise InputError(f"{source}: at most {top} ({why}), got {text[:40]}")
    return value


MAX_LIMIT = 1 << 48  # the largest value of any bound (256 TB, 2.8e14 pixels)


def pixels_text(n: int) -> str:
    """A pixel count for a message: `76800 pixels`, in megapixels from one (`16.8 MP`), never
    rounded to nothing (a bound of 1000 pixels was "0.0 MP")."""
    return f"{n / 1e6:.1f} MP" if n >= 1_000_000 else f"{n} pixels"


def bytes_text(n: int) -> str:
    """A byte count for a message: `1000 bytes`, `12.6 MB`, `1.6 GB`."""
    if n >= 1_000_000_000:
        return f"{n / 1e9:.1f} GB"
    return f"{n / 1e6:.1f} MB" if n >= 1_000_000 else f"{n} bytes"


def over_limit(name: str, amount: str | None = None) -> str:
    """The one shape of every message about a bound: `AMOUNT, over the LIMIT limit (NAME;
    raise it with `limit` NAME=N or SLAMRELOC_<NAME>)`, LIMIT in pixels, bytes or a count as the
    bound's name says (`amount`: what the input needs, or None)."""
    value = getattr(limits(), name)
    shown = (pixels_text(value) if name.endswith("_pixels") else
             bytes_text(value) if name.endswith("_bytes") else str(value))
    return (f"{'' if amount is None else amount + ', '}over the {shown} limit ({name}; raise "
            f"it with `limit` {name}=N or {ENV_PREFIX}{name.upper()})")


_current: InputLimits | None = None


def limits() -> InputLimits:
    """The bounds in force: the defaults, overridden by SLAMRELOC_<NAME> environment variables
    and then by `set_limits`."""
    global _current
    if _current is None:
        _current = _from_environment()
    return _current


def set_limits(**overrides: int) -> InputLimits:
    """Replace some bounds (e.g. `set_limits(max_image_pixels=50_000_000)`); returns them all.
    The others stay as `limits()` has them (the environment is read first, if not yet)."""
    global _current
    _current = replace(limits(), **overrides)
    return _current


def use_limits(bounds: InputLimits) -> InputLimits:
    """Make `bounds` the bounds in force, all of them as given, without reading this process's
    environment: how a Ray Serve map replica takes its driver's `limits()` (the driver's
    `--limit` and SLAMRELOC_<NAME> variables), whatever its own environment says."""
    global _current
    if not isinstance(bounds, InputLimits):
        raise InputError(f"bounds must be InputLimits, got {type(bounds).__name__}")
    _current = bounds
    return _current


def parse_limits(items: list[str]) -> dict[str, int]:
    """`["max_image_pixels=50000000", ...]` (the CLI's `--limit NAME=VALUE`) -> set_limits'
    kwargs. Each VALUE by `whole_limit`; a NAME given twice is refused (which one was meant?)."""
    names = [f.name for f in fields(InputLimits)]
    out: dict[str, int] = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.replace("-", "_")  # no blanks around it, as around the value
        if not sep or name not in names:
            raise InputError(f"`limit` {item[:80]!r}: expected NAME=VALUE with NAME one of "
                             f"{', '.join(names)}")
        value = whole_limit(text, f"`limit` {item[:80]!r}", name)
        if name in out:
            raise InputError(f"`limit` {name} is given twice ({str(out[name])[:24]} and "
                             f"{str(value)[:24]}): give each bound once")
        out[name] = value
    return out
