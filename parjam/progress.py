"""Progress lines on rank 0 only (quiet with -q)."""

import sys
import time


class Progress:
    def __init__(self, comm=None, quiet=False, prefix=""):
        rank = comm.Get_rank() if comm is not None else 0
        self.enabled = (not quiet) and rank == 0
        self.prefix = prefix
        self.t0 = time.time()

    def __call__(self, msg):
        if self.enabled:
            print(f"[{time.time() - self.t0:8.1f} s] {self.prefix}{msg}", file=sys.stderr,
                  flush=True)

    def sub(self, prefix):
        child = Progress(quiet=not self.enabled, prefix=self.prefix + prefix)
        child.t0 = self.t0
        return child

    def throttled(self, interval=10.0):
        """A callable printing at most once per ``interval`` seconds (for inner loops such as
        FIRE steps, whose count per second varies by orders of magnitude with N)."""
        last = [time.time()]

        def emit(msg):
            now = time.time()
            if now - last[0] >= interval:
                last[0] = now
                self(msg)

        return emit
