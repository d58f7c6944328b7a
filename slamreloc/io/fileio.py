"""Bounded file reads, and atomic file writes (a file, a JSON report): nothing the user had is
lost or left half-written."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from slamreloc.errors import InputError


def read_bytes(path: str | Path, what: str, limit: int) -> bytes:
    """The bytes of a file of at most `limit` bytes; InputError naming it otherwise."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found")
    try:
        size = path.stat().st_size
        if size > limit:
            raise InputError(f"{path}: {size} bytes, too large for a {what} file (limit "
                             f"{limit} bytes)")
        return path.read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read {what} ({err.strerror or err})") from None


def check_outputs(outputs: dict[str, str | Path | None],
                  inputs: dict[str, str | Path | None], folders: tuple[str, ...] = ()) -> None:
    """A command never writes where it only reads, nor over something that is not its own kind
    of output. InputError, before any work, unless each output path (keyed by how the user
    named it, e.g. "--report") is apart from every input (keyed by what it is, e.g. "the map":
    not the same file, not inside an input folder, not a folder holding one), apart from the
    other outputs, and absent or a regular file (a folder for the outputs named in `folders`):
    never a device, a pipe or a socket, which an atomic rename would replace. Symbolic links
    are followed."""
    ins = {what: Path(p).resolve() for what, p in inputs.items() if p is not None}
    seen: dict[Path, str] = {}
    for option, out in outputs.items():
        if out is None:
            continue
        target = Path(out).resolve()
        if target in seen:
            raise InputError(f"{out}: {option} and {seen[target]} name the same path")
        seen[target] = option
        if target.exists():
            want_dir = option in folders
            if want_dir and not target.is_dir() or not want_dir and not target.is_file():
                kind = "a folder" if target.is_dir() else "not a regular file"
                raise InputError(f"{out}: {option} exists and is {kind}; refusing to replace it")
        for what, src in ins.items():
            if target == src:
                problem = f"is {what}, which this command only reads"
            elif src.is_dir() and target.is_relative_to(src):
                problem = f"lies inside {what} ({src}), which this command only reads"
            elif src.is_relative_to(target):
                problem = f"would hold {what} ({src}), which this command only reads"
            else:
                continue
            raise InputError(f"{out}: {option} {problem}; write it elsewhere")


@contextmanager
def atomic_file(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path` (same suffix); rename it over `path` on success,
    remove it on failure."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json(path: str | Path, data: dict) -> None:
    """Write `data` as indented JSON, atomically (strict JSON: a NaN or infinity is an error,
    never a `NaN` token other readers refuse)."""
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, allow_nan=False))
