"""Helpers shared by the tests that run the whole pipeline on a small synthetic sequence, and a deep equality of
plain state data (checkpoints, ``state_dict`` outputs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

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


def assert_same(a, b, where: str = "state") -> None:
    """Deep equality of plain state data (dicts, lists, tuples, numpy arrays bit for bit, numbers)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), f"{where}: keys {list(a)} != {list(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), f"{where}: lengths differ"
        for n, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{n}]")
    elif isinstance(a, np.ndarray):
        b = np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, f"{where}: {a.dtype}{a.shape} != {b.dtype}{b.shape}"
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), f"{where}: values differ"
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"
