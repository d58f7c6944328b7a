"""Bounds on untrusted input, checked before anything is allocated for it.

Every reader takes its bound from here, so one setting covers the CLI, the Python API and a
service: the image decoder checks `max_image_pixels` against the header before it decodes, a
feature extractor checks the pixels it will work on, JSON readers check size and nesting depth.

Raise a bound with the CLI's global option (`slamreloc --limit max_image_pixels=50000000
localize ...`), the environment (`SLAMRELOC_MAX_IMAGE_PIXELS=50000000`), or `set_limits(...)`
in Python: a whole number in ASCII digits (`slamreloc.io.numbers`), each bound given once. The
defaults keep every command under ~2 GB of memory on any input (BENCHMARKS.md, "Input
bounds"); docs/formats.md lists them.
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


def _from_environment() -> InputLimits:
    known = {ENV_PREFIX + f.name.upper() for f in fields(InputLimits)}
    stray = sorted(n for n in os.environ if n.startswith((ENV_PREFIX + "MAX_",
                                                          ENV_PREFIX + "MIN_")) and n not in known)
    if stray:  # a misspelt bound would be ignored: the user believes it holds
        raise InputError(f"environment variable {stray[0][:80]} names no bound (one of "
                         f"{', '.join(sorted(known))})")
    overrides = {}
    for f in fields(InputLimits):
        name = ENV_PREFIX + f.name.upper()
        text = os.environ.get(name)
        if text is None:
            continue
        overrides[f.name] = whole_limit(text, f"environment variable {name}", f.name)
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
    raise it with `limit` NAME=N or SLAMRELOC_NAME)`, LIMIT in pixels, bytes or a count as the
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
    """Replace some bounds (e.g. `set_limits(max_image_pixels=50_000_000)`); returns them all."""
    global _current
    _current = replace(limits(), **overrides)
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
