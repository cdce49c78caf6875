"""The process-wide random number generators of a run: seeded from the run's ``seed`` at its start, and their
states captured / restored with a checkpoint.

Global RNGs: Python's ``random``, numpy's legacy ``np.random``, torch's CPU generator (and CUDA's when
present). The run's own components draw from generators they own (the field's torch generator and
numpy ``Generator``, seeded from ``field.seed`` and checkpointed with the field); seeding the globals guards the
libraries that reach for them.

What is *not* a generator but still limits bit-reproducibility: multi-threaded reductions whose order depends on
the thread schedule. On the CPU, with the same thread counts, the field (torch CPU kernels, the numba kernels'
static per-thread split) and GTSAM repeat bit for bit; Open3D's multi-threaded RGB-D odometry and ICP do not
(Open3D 0.20 runs them on its own thread pool, whatever ``OMP_NUM_THREADS`` says: two registrations of the same
frames differ by ~1e-6 m, and a gate decided on the edge turns that into centimetres over a run).
:func:`open3d_threads` with ``deterministic`` (the run config's key) runs Open3D on one thread. Open3D's own
multi-scale RGB-D odometry is not reproducible even then on every CPU (its IPP Gaussian filter depends on the
image's address), so :mod:`lrslam.frontend.rgbd_pyramid` builds that pyramid in numpy. On a GPU, torch's atomic
adds in the backward pass are not reproducible either.
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

__all__ = ["global_rng_state", "open3d_threads", "seed_everything", "set_global_rng_state"]


def seed_everything(seed: int) -> None:
    """Seed Python's, numpy's and torch's (CPU and CUDA) global RNGs with ``seed`` (>= 0). Open3D's is left
    alone: nothing in lrslam draws from it (no RANSAC), and importing Open3D for it would slow every field-only
    run's start and exit."""
    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)  # also seeds every CUDA device


def global_rng_state() -> dict[str, Any]:
    """The global RNG states of :func:`seed_everything` as plain Python / numpy data."""
    import torch

    kind, key, pos, has_gauss, gauss = np.random.get_state()
    state = {"python": random.getstate(),
             "numpy": {"kind": kind, "key": key.astype(np.int64), "pos": int(pos), "has_gauss": int(has_gauss),
                       "gauss": float(gauss)},
             "torch": torch.get_rng_state().numpy().copy()}
    if torch.cuda.is_available():
        state["torch_cuda"] = [s.numpy().copy() for s in torch.cuda.get_rng_state_all()]
    return state


def set_global_rng_state(state: dict[str, Any]) -> None:
    """Restore :func:`global_rng_state` output."""
    import torch

    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    n = state["numpy"]
    np.random.set_state((n["kind"], np.asarray(n["key"]).astype(np.uint32), n["pos"], n["has_gauss"], n["gauss"]))
    torch.set_rng_state(torch.as_tensor(state["torch"], dtype=torch.uint8))
    if "torch_cuda" in state and torch.cuda.is_available() and len(state["torch_cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all([torch.as_tensor(s, dtype=torch.uint8) for s in state["torch_cuda"]])


@contextmanager
def open3d_threads(deterministic: bool) -> Iterator[None]:
    """While inside, Open3D runs on one thread when ``deterministic`` (else unchanged); its previous thread
    count comes back after."""
    if not deterministic:
        yield
        return
    import open3d as o3d

    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(before)
