"""A tiny finished batch shared by the batch and report tests (built once per session, see conftest.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

from lrslam.tools.batch_exec import SequentialExecutor

# tiny and fast (plumbing, not accuracy): 5 frames, few iterations, coarse mesh, no per-run plot
TINY = ["field.tracking.iters=3", "field.mapping.iters=3", "field.mapping.first_iters=10",
        "field.tracking.n_rays=128", "field.mapping.n_rays=256", "field.mesh.resolution=0.1",
        "output.eval_mesh_points=2000", "output.plots=false", "dataset.options.max_frames=5"]


class Recording(SequentialExecutor):
    """The in-process executor, remembering which jobs it was given."""

    def __init__(self):
        super().__init__(1)
        self.ran: list[str] = []

    def run(self, jobs, batch_dir, on_start):
        self.ran += [j["name"] for j in jobs]
        yield from super().run(jobs, batch_dir, on_start)


def make_sequences(root: Path) -> dict[str, Path]:
    """a/room and b/room (same folder name), bad/room (its 2nd depth image is corrupt: fails inside the job)."""
    from lrslam.datasets.synth.writer import generate

    a = generate(root / "a" / "room", scene="room", trajectory="loop", n_frames=6, seed=1, width=160, height=120,
                 show_progress=False)
    shutil.copytree(a, root / "b" / "room")
    shutil.copytree(a, root / "bad" / "room")
    second = sorted((root / "bad" / "room" / "depth").iterdir())[1]
    second.write_bytes(b"not a png")
    return {"a": a, "b": root / "b" / "room", "bad": root / "bad" / "room"}


def finished_batch(root: Path) -> dict:
    """A finished batch in ``root``: 3 sequences x (field, 2 seeds + frontend) = 9 jobs, the 3 of bad/room
    failing. Returns root, seqs, jobs, out (the batch folder) and the outcome."""
    from lrslam.tools.batch import run_grid
    from lrslam.tools.batch_grid import expand_grid

    seqs = make_sequences(root)
    jobs = expand_grid([str(seqs[k]) for k in ("a", "b", "bad")], ["field", "frontend"], seeds=2,
                       preset="synthetic", overrides=TINY)
    out = root / "out"
    outcome = run_grid(jobs, out, SequentialExecutor(1), progress=False)
    return {"root": root, "seqs": seqs, "jobs": jobs, "out": out, "outcome": outcome}
