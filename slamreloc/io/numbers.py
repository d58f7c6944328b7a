"""The one rule for a number written as text, in files (pose files, COLMAP text models,
intrinsics and pose matrices, lists) and on the command line: plain ASCII decimal.

A number is an optional sign, ASCII digits with an optional fraction, and an optional exponent
(`-1.5`, `2e-3`, `.5`, `7.`); a whole number has no fraction or exponent. Python's `float()`
and `int()` take more, none of which a pose or a calibration file means: digit separators
(`1_000`), other scripts' digits (`٣`), surrounding blanks, `nan`, `inf`, `infinity`. Those
are refused, as is a number too large for a float (`1e999`). JSON numbers follow JSON's own
grammar, which is ASCII decimal too (`slamreloc.io.jsonio`).
"""

from __future__ import annotations

import math
import re

from slamreloc.errors import InputError

DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
WHOLE = re.compile(r"[+-]?[0-9]+")
MAX_DIGITS = 400  # characters: beyond them a number is not a value but an attack on int()
# the rule in words, ending every message that refuses a value by it
DECIMAL_WORDS = "numbers are plain ASCII decimals such as -1.5 or 2e-3"
WHOLE_WORDS = "whole numbers are plain ASCII digits with an optional sign, such as 12"


def written_as_number(word: str) -> bool:
    """Whether `word` is written as a number (a decimal, or nan / inf), even one no float
    holds (`1e400`): a field that is no name, to be checked as the number it means to be."""
    return bool(DECIMAL.fullmatch(word)) or word.lower().lstrip("+-") in ("nan", "inf",
                                                                          "infinity")


def number_problem(text: str, integer: bool = False) -> str | None:
    """Why `text` is not a number by the rule above (a whole number with `integer`): None
    when it is one."""
    if len(text) > MAX_DIGITS:
        return f"a number of {len(text)} characters"
    if not (WHOLE if integer else DECIMAL).fullmatch(text):
        return "not a whole number" if integer else "not a number"
    if not integer and not math.isfinite(float(text)):
        return "beyond the range of a number"
    return None


def parse_number(text: str, source: str, what: str = "value") -> float:
    """`text` as a float by the rule above; InputError `SOURCE: WHAT is not a number ('1_0')`
    otherwise (`source` names the file and line, or the option)."""
    problem = number_problem(text)
    if problem:
        raise InputError(f"{source}: {what} is {problem} ({text[:40]!r}; {DECIMAL_WORDS})")
    return float(text)


def parse_whole(text: str, source: str, what: str = "value") -> int:
    """`text` as an int by the rule above (ASCII digits, optional sign); InputError naming
    `source` otherwise."""
    problem = number_problem(text, integer=True)
    if problem:
        raise InputError(f"{source}: {what} is {problem} ({text[:40]!r}; {WHOLE_WORDS})")
    return int(text)
