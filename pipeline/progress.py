"""Progress of long work, on stderr, so a user can tell a slow run from a stuck one.

On an interactive terminal (stderr is a TTY) each task gets a tqdm bar. Otherwise (CI, a log file, a
pipe) each task prints plain lines, never carriage returns:

    [pag] nerf_fit window 2: validation render 5/30 (3.1 s)

one per unit of work, at most one per `interval_s` seconds per task (the first unit of each phase and
the last unit always get a line); the seconds in brackets are those since the task's previous line.
`enabled=False` (`run.progress=false`, `--no-progress`) prints nothing.

Crash tests: when the environment variable PAG_HOLD_AT is set, a process that formats a progress line
containing that text prints the line and then sleeps forever, so a test can kill the run at a known
point (during ingest, after the first NeRF window, ...). Whether or not the line is shown does not
matter; the text is the same in both modes.
"""
from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")
HOLD_ENV = "PAG_HOLD_AT"


def interactive() -> bool:
    """True when stderr is a terminal (bars), False for a pipe or a file (lines)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def say(msg: str) -> None:
    """One status line on stderr."""
    print(f"[pag] {msg}", file=sys.stderr, flush=True)


def _hold_if_asked(line: str) -> None:
    pattern = os.environ.get(HOLD_ENV)
    if pattern and pattern in line:
        say(f"holding at {pattern!r} ({HOLD_ENV} is set): {line}")
        while True:
            time.sleep(3600)


def _fmt(v: Any) -> str:
    return f"{v:.3g}" if isinstance(v, float) else str(v)


class Tracker:
    """Progress of one task (a stage's loop, one NeRF window): a bar or lines, as `interactive()` says.

    `update(done, total, phase, info)` records that `done` of `total` units of `phase` are finished;
    `finish(msg)` ends the task with a last line (lines mode) or closes the bar.
    """

    def __init__(self, label: str, total: int | None = None, enabled: bool = True, interval_s: float = 2.0,
                 position: int | None = None, bars: bool | None = None):
        if interval_s < 0:
            raise ValueError(f"progress interval_s must be >= 0, got {interval_s}")
        self.label, self.total, self.enabled, self.interval_s = label, total, enabled, interval_s
        self.bars = interactive() if bars is None else bars
        self.phase: str | None = None
        self.t_start = self.t_line = time.perf_counter()
        self.last_line = float("-inf")
        self.bar = None
        self.closed = False
        if enabled and self.bars:
            self.bar = tqdm(total=total, desc=label, position=position, leave=False, dynamic_ncols=True)

    def update(self, done: int, total: int | None = None, phase: str = "", info: dict[str, Any] | None = None) -> None:
        if self.closed:
            return
        total = self.total if total is None else total
        now = time.perf_counter()
        extra = " ".join(f"{k}={_fmt(v)}" for k, v in (info or {}).items())
        line = (f"{self.label}: {phase + ' ' if phase else ''}{done}/{total if total is not None else '?'}"
                f"{' ' + extra if extra else ''} ({now - self.t_line:.1f} s)")
        new_phase = phase != self.phase
        self.phase = phase
        if self.bar is not None:
            if total is not None:
                self.bar.total = total
            self.bar.n = done
            self.bar.set_description_str(f"{self.label}{': ' + phase if phase else ''}", refresh=False)
            if info:
                self.bar.set_postfix({k: _fmt(v) for k, v in info.items()}, refresh=False)
            self.bar.refresh()
        elif self.enabled and (new_phase or done == total or now - self.last_line >= self.interval_s):
            say(line)
            self.last_line = self.t_line = now
        _hold_if_asked(line)

    def finish(self, msg: str = "") -> None:
        if self.closed:
            return
        self.closed = True
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        line = f"{self.label}: {msg}" if msg else ""
        if line and self.enabled and not self.bars:
            say(line)
        if line:
            _hold_if_asked(line)


def iterate(it: Iterable[T], label: str, total: int | None = None, enabled: bool = True,
            interval_s: float = 2.0, unit: str = "") -> Iterator[T]:
    """Yield from `it`, reporting each finished item (a unit is finished when the next one is asked for)."""
    if total is None:
        try:
            total = len(it)  # type: ignore[arg-type]
        except TypeError:
            total = None
    tracker = Tracker(label, total, enabled, interval_s)
    done = 0
    try:
        for item in it:
            yield item
            done += 1
            tracker.update(done, total, unit)
    finally:
        tracker.finish()
