"""The stage progress line of ``mmflow run``: tasks done of the stage's total and the time it has left."""
from __future__ import annotations

import sys
import time


class Progress:
    """A one-line progress count with the time the stage has left: updated in place on a terminal,
    a line per ~10 % otherwise. Time left = elapsed / done x remaining (tasks of a stage are alike)."""

    def __init__(self, name, total, enabled, stream=sys.stdout, clock=time.monotonic):
        self.name, self.total, self.stream, self.clock = name, total, stream, clock
        self.enabled = enabled and total > 0
        self.tty = enabled and stream.isatty()
        self.last = -1
        self.t0 = clock()

    def text(self, done):
        left = ""
        if 0 < done < self.total:
            s = (self.clock() - self.t0) / done * (self.total - done)
            left = f", ~{s:.0f} s left" if s < 120 else f", ~{s / 60:.1f} min left"
        return f"[{self.name}] {done}/{self.total} tasks{left}"

    def update(self, done):
        if not self.enabled:
            return
        if self.tty:
            self.stream.write(f"\r{self.text(done)}\033[K")
            self.stream.flush()
        elif done * 10 // self.total > self.last * 10 // max(self.total, 1) or done == self.total:
            self.stream.write(self.text(done) + "\n")
        self.last = done

    def close(self):
        if self.enabled and self.tty:
            self.stream.write("\n")
