"""Progress bars with counts and rate (rich), shared by every long-running stage.

A bar that is still up when an error ends the command is erased, never drawn again after the
error: the CLI calls `stop_bars` before it prints the error line (which must be the last line
on stderr), and a `track` bar abandoned by its consumer (an exception in the loop body, the
generator closed whenever it is collected) stops without drawing its last frame."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TypeVar

from rich.console import Console
from rich.markup import escape
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                           TimeElapsedColumn, TimeRemainingColumn)

from slamreloc.errors import terminal_line

T = TypeVar("T")
console = Console(stderr=True, emoji=False)  # `:smile:` in a file name is no emoji
_SHOWN: list[Progress] = []  # bars started and not yet stopped, oldest first


def shown(text) -> str:
    """User text (a path, a file name) as a markup line of `console` shows it: rich markup
    escaped (`a[/x].tum` is no closing tag, `[red]z` no colour) and characters a terminal must
    not be sent as their escapes (`terminal_line`)."""
    return escape(terminal_line(str(text)))


class _Bar(Progress):
    """A Progress that registers itself while shown (`stop_bars`)."""

    abandoned = False

    def start(self) -> None:
        super().start()
        _SHOWN.append(self)

    def stop(self) -> None:
        if self in _SHOWN:
            _SHOWN.remove(self)
        if self.abandoned:  # nothing more: no last frame, no blank line after it
            self.live.stop()
        else:
            super().stop()

    def abandon(self) -> None:
        """Stop and erase the bar (it was left unfinished: its last frame would be noise)."""
        self.abandoned = True
        self.live.transient = True
        self.stop()


def make_progress() -> Progress:
    return _Bar(TextColumn("{task.description:<24}"), BarColumn(), MofNCompleteColumn(),
                TextColumn("[cyan]{task.fields[rate]}"),
                TimeElapsedColumn(), TimeRemainingColumn(), console=console,
                transient=False)


def stop_bars() -> None:
    """Erase every bar still shown, newest first: an error is about to be printed and must
    be the last line (no bar redrawn below it)."""
    while _SHOWN:
        _SHOWN[-1].abandon()


def track(items: Iterable[T], description: str, total: int | None = None,
          enabled: bool = True) -> Iterator[T]:
    """Iterate with a bar showing done/total, items per second and time left."""
    if not enabled:
        yield from items
        return
    total = total if total is not None else (len(items) if hasattr(items, "__len__") else None)
    with make_progress() as bar:
        task = bar.add_task(description, total=total, rate="")
        try:
            for item in items:
                yield item
                speed = bar.tasks[0].speed
                bar.update(task, advance=1, rate=f"{speed:6.1f} it/s" if speed else "")
        except GeneratorExit:  # the consumer stopped early (an error, or it had enough)
            bar.abandon()
            raise
        except BaseException:  # the items failed: the error follows, the bar must not
            bar.abandon()
            raise
