"""Helpers shared by the tests that run the whole pipeline on a small synthetic sequence."""

from __future__ import annotations

from pathlib import Path

# tiny and fast: these settings check plumbing, not accuracy (accuracy has its own tests and benchmarks)
TINY = ["field.tracking.iters=3", "field.mapping.iters=3", "field.mapping.first_iters=30",
        "field.tracking.n_rays=256", "field.mapping.n_rays=512"]


def synthetic_room(folder: Path, n_frames: int, seed: int) -> Path:
    """A 160x120 synthetic room on a loop trajectory (TUM layout + scene.yaml), written into ``folder``."""
    from lrslam.datasets.synth.writer import generate

    return generate(folder, scene="room", trajectory="loop", n_frames=n_frames, seed=seed, width=160, height=120,
                    show_progress=False)


def fail_at_frame(monkeypatch, index: int, message: str) -> None:
    """Make the runner raise ``RuntimeError(message)`` when it reaches frame ``index`` (a crash mid-run)."""
    from lrslam.pipeline.runner import SlamRunner

    real_step = SlamRunner.step

    def failing_step(self, frame):
        if frame.index == index:
            raise RuntimeError(message)
        return real_step(self, frame)

    monkeypatch.setattr(SlamRunner, "step", failing_step)
