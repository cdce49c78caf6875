"""Wall-clock stage timers for the per-stage breakdown in ``metrics.json``."""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager

__all__ = ["StageTimer"]


class StageTimer:
    """Accumulates seconds and call counts per named stage."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    @contextmanager
    def __call__(self, stage: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - t0
            self.calls[stage] += 1

    def state_dict(self) -> dict:
        """Seconds and calls so far, for checkpoints."""
        return {"seconds": dict(self.seconds), "calls": dict(self.calls)}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output (replaces the totals)."""
        self.seconds = defaultdict(float, state["seconds"])
        self.calls = defaultdict(int, state["calls"])

    def summary(self, n_frames: int) -> dict[str, dict[str, float]]:
        """``{stage: {total_s, calls, per_frame_s}}`` with per-frame = total / n_frames."""
        n = max(n_frames, 1)
        return {k: {"total_s": round(v, 4), "calls": self.calls[k], "per_frame_s": round(v / n, 5)}
                for k, v in self.seconds.items()}
