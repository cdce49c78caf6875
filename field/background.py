"""Mapping beside tracking (ESLAM runs its mapper in a second process; here a worker thread).

One mapping round runs in a worker thread while the main thread tracks the next frames against a **frozen copy**
of the field (``tracking_model``): the tracker never reads parameters the mapper is changing, and never toggles
their ``requires_grad`` (``SceneModel.frozen``) under the mapper's feet. The caller decides when a round's
result is taken (:meth:`BackgroundMapping.take`); only then is the copy refreshed. So the schedule -- which
field version tracks which frame -- follows the frame order alone, never thread timing, and a run repeats
bit for bit on the CPU (each thread has its own torch generator).

Threads: each of the two threads uses half the run's torch threads (at least one); torch's and numba's kernels
release the GIL, the Python between them does not. Measured on the TUM excerpt, field mode, 2 cores (README,
"Speed"): tracking on one core beside the mapper is ~1.5x slower than on two, but the overlap pays for it (same
settings: 2.37 -> 2.01 s/frame). A tracker on a map one round behind loses a fast camera: the runner waits for the
round after large motion (``schedule.background_wait_*``).
"""

from __future__ import annotations

import copy
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

import torch

from lrslam.field.model import SceneModel

__all__ = ["BackgroundMapping"]


class BackgroundMapping:
    """A one-worker mapping queue with a frozen tracking copy of ``model``.

    Args:
        model: the scene model the mapper optimises (the worker's).
        seed: seed of the tracking thread's own torch generator.
    """

    def __init__(self, model: SceneModel, seed: int) -> None:
        self.model = model
        self.tracking_model = copy.deepcopy(model)
        self.tracking_gen = torch.Generator().manual_seed(int(seed) + 1)
        self._threads_before = torch.get_num_threads()
        self.threads = max(1, self._threads_before // 2)
        torch.set_num_threads(self.threads)   # the tracking (main) thread's share
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="lrslam-mapper",
                                        initializer=torch.set_num_threads, initargs=(self.threads,))
        self._pending: Future | None = None
        self._result: object = None
        self._has_result = False

    @property
    def busy(self) -> bool:
        """A round was submitted and its result not yet taken."""
        return self._pending is not None or self._has_result

    def submit(self, fn: Callable[[], object]) -> None:
        """Run ``fn()`` (one mapping round on ``model``) in the worker. The previous round's result must have
        been taken (:meth:`take`)."""
        if self.busy:
            raise RuntimeError("background mapping: take() the previous round's result before submitting")
        self._pending = self._pool.submit(fn)

    def wait(self) -> None:
        """Block until the pending round finished (its exception, if any, is raised here); keeps its result for
        :meth:`take` and leaves the tracking copy as it was."""
        if self._pending is not None:
            fut, self._pending = self._pending, None
            self._result, self._has_result = fut.result(), True

    def take(self) -> object:
        """Wait for the pending round, refresh the tracking copy from ``model`` and return the round's result
        (None when no round was submitted)."""
        self.wait()
        if not self._has_result:
            return None
        out, self._result, self._has_result = self._result, None, False
        self.refresh()
        return out

    def refresh(self) -> None:
        """Copy ``model``'s current parameters into the tracking copy (no round may be running)."""
        with torch.no_grad():
            self.tracking_model.load_state_dict(self.model.state_dict())

    # ---------------------------------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        """The tracking copy, the tracking generator and a finished round's result not yet taken (the pending
        round is waited for first), as plain data."""
        self.wait()
        return {"tracking_model": {k: v.detach().cpu().numpy() for k, v in self.tracking_model.state_dict().items()},
                "tracking_gen": self.tracking_gen.get_state().numpy(),
                "result": self._result, "has_result": self._has_result}

    def load_state_dict(self, state: dict) -> None:
        self.tracking_model.load_state_dict({k: torch.as_tensor(v) for k, v in state["tracking_model"].items()})
        self.tracking_gen.set_state(torch.as_tensor(state["tracking_gen"], dtype=torch.uint8))
        self._pending, self._result, self._has_result = None, state["result"], bool(state["has_result"])

    def close(self) -> None:
        """Wait for the worker, stop it and give the main thread its torch threads back."""
        self._pool.shutdown(wait=True)
        torch.set_num_threads(self._threads_before)
