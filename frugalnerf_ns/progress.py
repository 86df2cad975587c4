"""Progress lines for anything that can take more than a few seconds (video frames, start-up's SIFT and
matching): plain, flushed lines, so a log file shows progress while the work runs (a progress bar shows only
when it finishes), one per ``every_seconds`` and at the first and last item."""

from __future__ import annotations

import sys
import time
from typing import Callable, Optional


def format_duration(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"


class Progress:
    """``label: <unit> done/total, rate, seconds per item, elapsed, ETA``."""

    def __init__(self, total: int, label: str, unit: str = "item", rate_unit: Optional[str] = None,
                 every_seconds: float = 10.0, write: Callable[[str], None] = print,
                 clock: Callable[[], float] = time.monotonic, quiet_seconds: float = 0.0) -> None:
        """``quiet_seconds``: no line before that much time has passed (work that ends sooner stays silent)."""
        self.total, self.label, self.unit, self.every, self.write, self.clock = total, label, unit, every_seconds, write, clock
        self.quiet = quiet_seconds
        self.rate_unit = rate_unit or f"{unit}s/s"
        self.done = 0
        self.start = clock()
        self.last_line: Optional[float] = None

    def line(self) -> str:
        elapsed = max(self.clock() - self.start, 1e-9)
        rate = self.done / elapsed
        eta = (self.total - self.done) / rate if rate > 0 else float("inf")
        eta_text = format_duration(eta) if eta != float("inf") else "?"
        return (f"{self.label}: {self.unit} {self.done}/{self.total}, {rate:.2f} {self.rate_unit} "
                f"({elapsed / max(self.done, 1):.1f} s/{self.unit}), elapsed {format_duration(elapsed)}, ETA {eta_text}")

    def tick(self, count: int = 1) -> None:
        self.done += count
        now = self.clock()
        if now - self.start < self.quiet:
            return
        if self.done in (count, self.total) or self.last_line is None or now - self.last_line >= self.every:
            self.last_line = now
            self.write(self.line())
            sys.stdout.flush()


def FrameProgress(total: int, label: str = "frugalnerf render", every_seconds: float = 10.0,  # noqa: N802
                  write: Callable[[str], None] = print, clock: Callable[[], float] = time.monotonic) -> Progress:
    """Progress of a video render: frames, fps, seconds per frame."""
    return Progress(total, label, "frame", "fps", every_seconds, write, clock)
