"""Watching a run: what :class:`lrslam.Slam` tells its observers (a live viewer, a logger, a test probe).

An observer implements :class:`SlamObserver` and is attached with ``Slam(..., observers=[obs])`` or
``slam.add_observer(obs)``. After every :meth:`~lrslam.Slam.track` it receives one frozen :class:`FrameEvent`;
after :meth:`~lrslam.Slam.finish`, the :class:`~lrslam.pipeline.runner.SlamResult`. A Slam without observers
builds no event (nothing extra is computed). Observers watch: they must not change the run (the poses they are
handed are copies; :attr:`FrameEvent.field` is read-only use of the map).

Poses are ``T_w_c``, (4, 4) float64, metres, in the run's world frame (the first frame's pose, identity unless
the run started at a given pose).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from lrslam.frame import Frame

if TYPE_CHECKING:  # annotations only (lrslam.pipeline.slam imports this module)
    from lrslam.pipeline.runner import SlamResult
    from lrslam.pipeline.slam import FrameResult

__all__ = ["FieldView", "FrameEvent", "SlamObserver"]


class FieldView(Protocol):
    """Read-only use of the run's field (:class:`lrslam.pipeline.parts.FieldMapper`)."""

    def render(self, T_w_c: np.ndarray, scale: int = 4,
               depth: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Depth (h, w) float32 metres and colour (h, w, 3) float32 in [0, 1] rendered at ``T_w_c`` at the pixels
        of ``image[::scale, ::scale]`` (``depth``: the frame's (H, W) metres, guides the samples)."""

    def mesh(self, keyframe_poses: dict[int, np.ndarray], resolution: float | None):
        """Marching-cubes mesh (``trimesh.Trimesh``, world metres) culled to what the keyframes saw."""


@dataclass(frozen=True)
class FrameEvent:
    """One tracked frame, as an observer sees it.

    frame: the :class:`~lrslam.frame.Frame` tracked (rgb (H, W, 3) uint8, depth (H, W) metres, K (3, 3)).
    result: the :class:`~lrslam.pipeline.slam.FrameResult` returned to the caller (pose ``T_w_c``, status,
    record). T_w_seed: (4, 4) the frame's seed (odometry or constant velocity). T_w_frontend: (4, 4) the
    frontend's own pose of the frame (odometry alone), None without a frontend. keyframe_ids: every keyframe so
    far (frame indices). stage_seconds: ``{stage: s}`` wall time each stage of the Slam spent on this frame
    (``seed``, ``refine``, ``keyframe``, ``map``, ``graph``, ``remap``; only the stages that ran). seconds: wall
    time of the whole :meth:`~lrslam.Slam.track` call. trajectory: returns ``(timestamps (N,) s, T_w_c (N, 4,
    4))`` of every frame so far, as they are now (O(N): call it when needed, inside ``on_frame``). field: the
    run's field, None without one.
    """

    frame: Frame
    result: FrameResult
    T_w_seed: np.ndarray
    T_w_frontend: np.ndarray | None
    keyframe_ids: tuple[int, ...]
    stage_seconds: dict[str, float]
    seconds: float
    trajectory: Callable[[], tuple[np.ndarray, np.ndarray]]
    field: FieldView | None = None

    @property
    def index(self) -> int:
        return self.result.index

    @property
    def timestamp(self) -> float:
        """Seconds, as given to :meth:`~lrslam.Slam.track`."""
        return self.result.timestamp

    @property
    def loop_edges(self) -> tuple[tuple[int, int], ...]:
        """Verified loop closures ``(i, j)`` (keyframe frame indices, j = this frame) added at this frame."""
        return tuple((int(i), int(j)) for i, j in self.result.record.loop_edges)

    @property
    def moved(self) -> dict[int, tuple[float, float]]:
        """``{keyframe: (metres, degrees)}``: the keyframes the pose graph moved at this frame, and by how much."""
        return dict(self.result.record.moved)

    @property
    def moved_from(self) -> dict[int, np.ndarray]:
        """``{keyframe: (3,) position (m)}`` of each moved keyframe before the graph's correction (its position
        after: ``trajectory()[1][keyframe, :3, 3]``)."""
        return {k: np.asarray(p, dtype=np.float64) for k, p in self.result.record.moved_from.items()}


class SlamObserver(Protocol):
    """Something that watches a run frame by frame (:class:`lrslam.pipeline.viewer.RerunViewer`)."""

    def on_frame(self, event: FrameEvent) -> None:
        """After each tracked frame."""

    def on_finish(self, result: SlamResult) -> None:
        """After :meth:`lrslam.Slam.finish` (the result holds the final poses and, when meshed, the mesh)."""
