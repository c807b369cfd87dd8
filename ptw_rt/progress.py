"""Progress on stderr for commands that take more than a few seconds: a bar when stderr is a terminal, plain
periodic lines otherwise (a log file or CI gets a line every ``every`` seconds, never carriage returns).

    bar = Progress(len(jobs), label="replay")       # counted work: bar.step("a.log") per job done
    bar = Progress(1.0, label="replay ride.blf")     # a share of one job: bar.update(0.42); bar.finish()
"""

from __future__ import annotations

import math
import sys
import time
from typing import IO

__all__ = ["Progress"]

_WIDTH = 30


class Progress:
    """A progress bar on stderr when it is a terminal; otherwise a plain line every ``every`` seconds.

    ``step()`` counts one unit done and shows it at once (jobs of a matrix or a directory). ``update(done)``
    sets the amount done (a share of one long job) and draws at most every ``interval`` seconds on a terminal,
    after ``delay`` seconds (a job done sooner shows nothing); ``finish()`` ends the bar's line.
    """

    def __init__(
        self,
        total: float,
        label: str = "matrix",
        stream: IO[str] | None = None,
        every: float = 10.0,
        *,
        delay: float = 0.0,
        interval: float = 0.1,
    ) -> None:
        self.total, self.label, self.done = total, label, 0.0
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every = every
        self.delay = delay
        self.interval = interval
        self.t0 = time.perf_counter()
        self._last = -math.inf  # last plain line (elapsed s)
        self._drawn = -math.inf  # last bar drawn (elapsed s)
        self._shown = False  # anything written (finish() ends the line only then)

    def _count(self) -> str:
        if float(self.total).is_integer() and float(self.done).is_integer() and self.total > 1:
            return f"{int(self.done)}/{int(self.total)}"
        return f"{100.0 * self.done / max(self.total, 1e-12):3.0f}%"

    def _bar(self, elapsed: float, what: str) -> None:
        fill = int(round(_WIDTH * min(1.0, self.done / max(self.total, 1e-12))))
        self.stream.write(
            f"\r{self.label} [{'#' * fill}{'.' * (_WIDTH - fill)}] {self._count()} {elapsed:5.0f} s {what[:32]:<32}"
        )
        self._shown = True

    def step(self, what: str = "") -> None:
        self.done += 1
        elapsed = time.perf_counter() - self.t0
        if self.tty:
            self._bar(elapsed, what)
            if self.done >= self.total:
                self.stream.write("\n")
                self._shown = False
        elif self.done >= self.total or elapsed - self._last >= self.every:
            self._last = elapsed
            self.stream.write(f"{self.label}: {self._count()} done, {elapsed:.0f} s ({what})\n")
        self.stream.flush()

    def update(self, done: float, what: str = "") -> None:
        self.done = done
        elapsed = time.perf_counter() - self.t0
        if elapsed < self.delay:
            return
        if self.tty:
            if elapsed - self._drawn >= self.interval:
                self._drawn = elapsed
                self._bar(elapsed, what)
                self.stream.flush()
        elif elapsed - max(self._last, self.delay) >= self.every or (self._last < 0 and self.every <= 0):
            self._last = elapsed
            self.stream.write(f"{self.label}: {self._count()} done, {elapsed:.0f} s {what}".rstrip() + "\n")
            self._shown = True
            self.stream.flush()

    def finish(self, what: str = "") -> None:
        """The job is done: the bar at 100 % and its line ended (if anything was shown)."""
        if not self._shown:
            return
        self.done = self.total
        elapsed = time.perf_counter() - self.t0
        if self.tty:
            self._bar(elapsed, what)
            self.stream.write("\n")
        else:
            self.stream.write(f"{self.label}: done, {elapsed:.0f} s {what}".rstrip() + "\n")
        self.stream.flush()
        self._shown = False
