"""The graph backend's policy: which measurements enter the keyframe pose graph, when it is solved, which corrected
poses are written back and which keyframes the field is re-mapped over.

:class:`GraphBackend` keeps the factors (:class:`~lrslam.backend.graph.PoseGraph`), the loop closer's keyframe
images (:class:`~lrslam.backend.loop_closure.LoopCloser`) and the frontend's chain since the last keyframe
(:class:`~lrslam.backend.keyframe_link.KeyframeLink`); every pose comes from the caller's trajectory, and it
returns a :class:`Correction` that says what to change. It never writes a pose itself.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field as dc_field, replace
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import Field

from lrslam.config import StrictModel
from lrslam.frame import Frame
from lrslam.geometry import inv, pose_error

if TYPE_CHECKING:  # annotations only: GTSAM, OpenCV and Open3D load when a graph is built, not on import
    from lrslam.backend.graph import PoseGraph
    from lrslam.backend.keyframe_link import KeyframeLink, KeyframeLinkMeasurement
    from lrslam.backend.loop_closure import LoopCloser, LoopConstraint
    from lrslam.frontend.odometry import OdometryResult

__all__ = ["BackendConfig", "Correction", "FactorRecord", "GraphBackend", "PoseLosses"]

log = logging.getLogger(__name__)

# (rgb, depth, [T_w_c ...]) -> the field's tracking loss of the frame at each pose, on the same rays
PoseLosses = Callable[[np.ndarray, np.ndarray, list[np.ndarray]], list[float]]


class BackendConfig(StrictModel):
    """How the pose graph is fed, when it is solved and when its result is written back and re-mapped for.

    factors: which measurements enter the graph: ``odometry`` (the frontend's own keyframe-to-keyframe
    estimate, :mod:`lrslam.backend.keyframe_link`), ``field`` (the relative pose of consecutive keyframes in
    the current trajectory, with the field tracker's information; re-stated from the current poses before every
    solve, so the graph never pulls the mapper's refinements back), ``loop`` (verified loop closures).
    optimise: ``on_loop`` solves when a loop with a real correction arrives (above ``loop_min_correction_*``;
    consistent re-observations only add their factor), ``every_keyframe`` at every keyframe.
    write_min_shift_*: a keyframe is overwritten only where the graph moved it more than this.
    remap_min_shift_m / remap_keyframes: a solve that moved some keyframe more than this re-maps the field over
    (at most) that many most-moved keyframes (``field.mapping.remap_iters`` iterations).
    loop_field_check: with a field, a loop that would correct the trajectory is kept only when the map agrees:
    the new keyframe's tracking loss at the pose the loop implies (``T_w_i T_i_j``) is at most
    ``(1 + loop_field_tolerance)`` times its loss at the current pose, on the same rays; otherwise the loop is
    dropped (logged and counted): the frontend's registration of two views is less precise than tracking
    against the whole map, and a loop the map disputes would pull an accurate trajectory toward its error."""

    factors: list[Literal["odometry", "field", "loop"]] = ["odometry", "field", "loop"]
    optimise: Literal["on_loop", "every_keyframe"] = "on_loop"
    loop_min_correction_m: float = Field(0.01, ge=0)
    loop_min_correction_deg: float = Field(1.0, ge=0)
    write_min_shift_m: float = Field(1e-4, ge=0)
    write_min_shift_deg: float = Field(0.01, ge=0)
    remap_min_shift_m: float = Field(0.005, ge=0)
    remap_keyframes: int = Field(20, gt=0)
    loop_field_check: bool = True
    loop_field_tolerance: float = Field(0.0, ge=0)


@dataclass(frozen=True)
class Correction:
    """What the backend decided at a keyframe.

    ``poses``: the keyframes to overwrite, ``{kf: T_w_kf}`` (only those the solve moved by more than the write
    threshold; empty when it did not solve); ``remap``: keyframe ids to re-map the field over, most-moved first;
    ``shifts``: ``{kf: (metres, degrees)}`` of each keyframe in ``poses``; ``solved``: whether the graph was
    solved; ``edges``: the verified loop closures added, as ``(i, j)`` keyframe ids (``j`` the new keyframe);
    ``link``: the frontend's direct registration ``T_i_j`` (4, 4) of the new keyframe to the previous one (None when
    it was rejected and the odometry chain stood in, or without an odometry factor)."""

    poses: dict[int, np.ndarray] = dc_field(default_factory=dict)
    remap: tuple[int, ...] = ()
    shifts: dict[int, tuple[float, float]] = dc_field(default_factory=dict)
    solved: bool = False
    edges: tuple[tuple[int, int], ...] = ()
    link: np.ndarray | None = None

    @property
    def loops(self) -> int:
        """How many verified loop closures were added."""
        return len(self.edges)


@dataclass(frozen=True)
class FactorRecord:
    """One between factor as it entered the graph (before any solve re-stated it), for calibration checks
    (:mod:`lrslam.evaluation.factors`): ``kind`` (``odometry``, ``field`` or ``loop``), keyframe ids ``i``, ``j``
    (frame indices), the measurement ``T_i_j`` (4, 4) and its ``information`` (6, 6; right perturbation,
    ``[rotation, translation]``)."""

    kind: str
    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray


class GraphBackend:
    """Keyframe pose graph with frontend, field and loop factors (see :class:`BackendConfig`).

    Args:
        cfg: the policy.
        graph: the GTSAM pose graph (``graph.optimiser`` lm or gnc: field factors are re-stated before each solve).
        loop_closer: loop detection and verification; link: the frontend's keyframe-to-keyframe measurement.
        field_default_information: (6, 6) information of a field factor whose keyframe had none.
        pose_losses: the field's tracking loss at given poses (for ``loop_field_check``), None without a field.
    """

    def __init__(self, cfg: BackendConfig, graph: PoseGraph, loop_closer: LoopCloser, link: KeyframeLink,
                 field_default_information: np.ndarray, pose_losses: PoseLosses | None = None):
        self.cfg = cfg
        self.graph, self.loop_closer, self.link = graph, loop_closer, link
        self._default_info = field_default_information
        self._pose_losses = pose_losses if cfg.loop_field_check else None
        self._last: int | None = None
        self.n_loops = self.n_solves = self.n_loops_disputed = 0
        self.measurements: list[FactorRecord] = []

    def state_dict(self) -> dict:
        """Factors (plain numpy, :meth:`PoseGraph.state`), the loop closer's keyframes, the frontend's chain since
        the last keyframe and the counters, for checkpoints."""
        return {"graph": self.graph.state(), "loop_closer": self.loop_closer.state_dict(),
                "link": self.link.state_dict(), "last": self._last, "n_loops": self.n_loops,
                "n_solves": self.n_solves, "n_loops_disputed": self.n_loops_disputed,
                "measurements": [vars(m).copy() for m in self.measurements]}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output."""
        self.graph = type(self.graph).from_state(self.graph.cfg, state["graph"])
        self.loop_closer.load_state_dict(state["loop_closer"])
        self.link.load_state_dict(state["link"])
        self._last = state["last"]
        self.n_loops, self.n_solves = int(state["n_loops"]), int(state["n_solves"])
        self.n_loops_disputed = int(state["n_loops_disputed"])
        self.measurements = [FactorRecord(**m) for m in state.get("measurements", [])]

    def start(self, frame: Frame, T_w_c0: np.ndarray) -> None:
        self.graph.add_keyframe(frame.index, T_w_c0)
        self.loop_closer.add_keyframe(frame.index, frame)
        self.link.start(frame.index, frame)
        self._last = frame.index

    def on_frame(self, odometry: OdometryResult | None) -> None:
        """Chain the frontend's increment of every frame (the odometry factor's fallback)."""
        if odometry is not None:
            self.link.accumulate(odometry)

    def on_keyframe(self, frame: Frame, poses: dict[int, np.ndarray], information: np.ndarray | None) -> Correction:
        """Add keyframe ``frame.index`` (its pose in ``poses``, every keyframe's current ``T_w_c``) with its
        factors; solve when a loop brings a real correction (or at every keyframe); return what to write back."""
        loops, link = self._add_factors(frame, poses, information)
        real = [lc for lc in loops if self._is_correction(lc)]
        if len(loops) > len(real):
            log.info("keyframe %d: %d loop(s) consistent with the trajectory (no solve for them)", frame.index,
                     len(loops) - len(real))
        edges = tuple((lc.i, lc.j) for lc in loops)
        T_link = link.T_i_j if link is not None and link.source == "registration" else None
        if not (real or self.cfg.optimise == "every_keyframe"):
            return Correction(edges=edges, link=T_link)
        return replace(self._solve(poses, edges), link=T_link)

    def _add_factors(self, frame: Frame, poses: dict[int, np.ndarray],
                     information: np.ndarray | None) -> tuple[list, KeyframeLinkMeasurement | None]:
        """Steps 1-3: the new keyframe's field, frontend and loop factors; returns the loops kept and the
        frontend's keyframe-to-keyframe measurement."""
        i, j, factors = self._last, frame.index, self.cfg.factors
        self.graph.add_keyframe(j)
        # 1. Field factor: the trajectory's relative pose, with the tracker's information.
        if "field" in factors:
            info = information if information is not None else self._default_info
            self._add("field", i, j, inv(poses[i]) @ poses[j], info)
        # 2. Frontend factor: its own keyframe-to-keyframe estimate.
        link = self.link.measure(j, frame)
        if "odometry" in factors and link is not None:
            self._add("odometry", link.i, link.j, link.T_i_j, link.information)
        # 3. Loops against earlier keyframes.
        loops = []
        if "loop" in factors:
            loops = self._agreed_by_field(self.loop_closer.detect(j, frame, poses), frame, poses)
            for lc in loops:
                self._add("loop", lc.i, lc.j, lc.T_i_j, lc.information)
        self.loop_closer.add_keyframe(j, frame)
        self._last = j
        self.n_loops += len(loops)
        return loops, link

    def _add(self, kind: str, i: int, j: int, T_i_j: np.ndarray, information: np.ndarray) -> None:
        """Add a between factor to the graph and to :attr:`measurements`."""
        add = {"field": self.graph.add_field_relative, "odometry": self.graph.add_odometry,
               "loop": self.graph.add_loop}[kind]
        add(i, j, T_i_j, information)
        self.measurements.append(FactorRecord(kind, int(i), int(j), np.array(T_i_j, dtype=np.float64),
                                              np.array(information, dtype=np.float64)))

    def _solve(self, poses: dict[int, np.ndarray], edges: tuple[tuple[int, int], ...]) -> Correction:
        """Step 4: solve from the trajectory's poses, field factors re-stated from them (the graph never reverts
        the mapper's refinements: only loops and the frontend's measurements move poses); then which keyframes
        to write (moved more than ``write_min_shift_*``) and to re-map (the most-moved, beyond
        ``remap_min_shift_m``)."""
        c = self.cfg
        for a, b in zip(list(poses)[:-1], list(poses)[1:]):
            self.graph.set_measurement("field", a, b, inv(poses[a]) @ poses[b])
        self.n_solves += 1
        solution = self.graph.optimise(poses)
        written, shifts = {}, {}
        for k, T in solution.items():
            if k not in poses:
                continue
            d_t, d_r = pose_error(poses[k], T)
            if d_t > c.write_min_shift_m or d_r > c.write_min_shift_deg:
                written[k], shifts[k] = T, (d_t, d_r)
        big = [k for k, (d_t, _) in sorted(shifts.items(), key=lambda kv: -kv[1][0]) if d_t > c.remap_min_shift_m]
        return Correction(written, tuple(big[: c.remap_keyframes]), shifts, True, edges)

    def _is_correction(self, lc: LoopConstraint) -> bool:
        return lc.correction_m > self.cfg.loop_min_correction_m or lc.correction_deg > self.cfg.loop_min_correction_deg

    def _agreed_by_field(self, loops: list[LoopConstraint], frame: Frame,
                         poses: dict[int, np.ndarray]) -> list[LoopConstraint]:
        """The loops the map does not dispute (see ``BackendConfig.loop_field_check``): consistent
        re-observations always; corrections only where the new keyframe fits the field at the loop's pose at
        least as well as at its current one."""
        if self._pose_losses is None or not any(self._is_correction(lc) for lc in loops):
            return loops
        j = frame.index
        corrections = [lc for lc in loops if self._is_correction(lc)]
        losses = self._pose_losses(frame.rgb, frame.depth, [poses[j]] + [poses[lc.i] @ lc.T_i_j for lc in corrections])
        kept = [lc for lc in loops if not self._is_correction(lc)]
        for lc, loss in zip(corrections, losses[1:]):
            if np.isfinite(loss) and np.isfinite(losses[0]) and loss > losses[0] * (1.0 + self.cfg.loop_field_tolerance):
                self.n_loops_disputed += 1
                log.info("loop %d-%d dropped: the map disputes its correction (%.3f m, %.2f deg; loss %.4g vs %.4g "
                         "at the current pose)", lc.i, j, lc.correction_m, lc.correction_deg, loss, losses[0])
            else:
                kept.append(lc)
        return kept
