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

from lrslam.backend.calibration import GapNoise, calibrated

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
    calibrate / loop_max_chi2 / final_refine: see the fields.
    loop_field_check (off by default): with a field, a loop that would correct the trajectory is kept only when
    the map agrees: the new keyframe's tracking loss at the pose the loop implies (``T_w_i T_i_j``) is at most
    ``(1 + loop_field_tolerance)`` times its loss at the current pose, on the same rays; otherwise the loop is
    dropped (logged and counted). Off because the map near the camera was built from the same drifted poses the
    loop would correct, and sides with them: on the full TUM fr1/xyz it disputed 163-172 of 375 loops, among them
    registrations at fitness 0.79-0.93 that were right about a 2-3 cm drift. Loops are judged by geometry (the
    registration's gates) and by the graph's consistency (``loop_max_chi2`` on calibrated informations,
    ``calibrate``) instead; docs/BENCHMARKS.md sections 14-15."""

    factors: list[Literal["odometry", "field", "loop"]] = ["odometry", "field", "loop"]
    optimise: Literal["on_loop", "every_keyframe"] = "on_loop"
    loop_min_correction_m: float = Field(0.01, ge=0)
    loop_min_correction_deg: float = Field(1.0, ge=0)
    write_min_shift_m: float = Field(1e-4, ge=0)
    write_min_shift_deg: float = Field(0.01, ge=0)
    remap_min_shift_m: float = Field(0.005, ge=0)
    remap_keyframes: int = Field(20, gt=0)
    loop_field_check: bool = False
    loop_field_tolerance: float = Field(0.0, ge=0)
    calibrate: bool = Field(True, description="with the run's measured noise (fused mode), every factor's "
                            "information calibrated from it (lrslam.backend.calibration) before each online solve "
                            "(the final refinement always is). The sources' own informations are off by an order "
                            "of magnitude either way (fr1/xyz against ground truth: the field's 26x too strong, so "
                            "the loops could not move it; 3 seeds with the map's loop check off: fr1/xyz 1.30 -> "
                            "1.10 cm, TUM excerpt 2.30 -> 2.26; docs/BENCHMARKS.md section 15). With the map's check "
                            "on it cost TUM fr1/rpy 2.29 -> 2.54 and 7-Scenes 3.79 -> 4.60 (12-05)")
    odometry_factor: Literal["registration", "chain"] = Field(
        "registration", description="the frontend's keyframe-to-keyframe factor: its direct registration of the "
        "new keyframe to the previous one, or the chain of its per-frame poses (calibrated to the chain's measured "
        "noise; with odometry.model on, 7-Scenes every 4th frame: deterministic 3 seeds 2.96 cm, threaded 4 runs 3.51; "
        "lrslam.backend.keyframe_link, docs/BENCHMARKS.md section 21)")
    calibrate_registrations: bool = Field(True, description="with calibrate: the "
                                          "registrations' (odometry and loop factors) informations are calibrated "
                                          "too, in the online solves and the final refinement. False: they "
                                          "keep the information their registration states (its point-to-plane "
                                          "Hessian at the measured inlier RMSE, at least "
                                          "registration.information_sigma) and only the field's is calibrated; "
                                          "for data whose colour is registered to its depth only approximately "
                                          "(7-Scenes), where "
                                          "the noise estimate compares two RGB-D registrations that share that "
                                          "error (lrslam.backend.calibration)")
    loop_max_chi2: float = Field(60.0, ge=0, description="after a solve, a loop whose normalised squared residual "
                                 "exceeds this is removed as inconsistent with the graph and the graph re-solved, "
                                 "worst first; 0 = off. Chi-square with 6 dof would put it at 22.46 (99.9 %) if a "
                                 "loop's calibrated information were its error's, but a loop (wide baseline, "
                                 "keyframes at half size) errs more than the keyframe registrations its weight is "
                                 "calibrated from: against ground truth its chi2 / dof is 85 on TUM fr1/xyz and "
                                 "fr1/rpy, and 22.46 removed true loops there (fr1/xyz 1.08 -> 1.01 cm at 60, "
                                 "1.04 at 120, 1.12 off; fr1/rpy excerpt 2.07 -> 2.02, 2.30 off; "
                                 "docs/BENCHMARKS.md section 19). A wrong loop lies far above either")
    final_refine: bool = Field(False, description="at the end of a run: one solve over every keyframe and factor "
                               "(calibrated), its corrections written and the field re-mapped over the most-moved "
                               "keyframes")
    final_refine_when: Literal["field_gated", "always"] = Field(
        "field_gated", description="field_gated: the final refinement runs only where the run's noise estimate gated "
        "the field out of the per-frame fusion in both blocks (the frontend is the more precise source: it then "
        "replaces the frame-to-frame chain by the keyframe registrations; fast synthetic orbit 0.86 -> 0.35 cm). "
        "Where the field takes a share, the online keyframe poses carry the mapper's joint refinement, which "
        "the field's tracked poses lack, and the refinement made them worse (synthetic loop 0.45 -> 0.65, TUM "
        "fr1/rpy excerpt 2.37 -> 2.59 cm, one seed; docs/BENCHMARKS.md)")
    final_refine_field: bool = Field(True, description="the field's keyframe poses take part in the final solve "
                                     "(False: the frontend's registrations and the loops alone)")


@dataclass(frozen=True)
class Correction:
    """What the backend decided at a keyframe.

    ``poses``: the keyframes to overwrite, ``{kf: T_w_kf}`` (only those the solve moved by more than the write
    threshold; empty when it did not solve); ``remap``: keyframe ids to re-map the field over, most-moved first;
    ``shifts``: ``{kf: (metres, degrees)}`` of each keyframe in ``poses``; ``solved``: whether the graph was
    solved; ``edges``: the verified loop closures added, as ``(i, j)`` keyframe ids (``j`` the new keyframe);
    ``link``: the frontend's direct registration ``T_i_j`` (4, 4) of the new keyframe to the previous one (None when
    it was rejected and the odometry chain stood in, or without an odometry factor; a weak one is given: it adds no
    factor, but its error belongs in the noise estimate)."""

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

    @property
    def max_shift_m(self) -> float:
        """The largest move of a written keyframe in metres (0 when none was written)."""
        return max((m for m, _ in self.shifts.values()), default=0.0)


@dataclass(frozen=True)
class FactorRecord:
    """One measurement as it entered the graph (before any solve re-stated it), for calibration checks
    (:mod:`lrslam.evaluation.factors`) and the final refinement: ``kind`` (``odometry``, ``field`` or ``loop``
    between factors; ``field_pose``: the field's own tracked pose of keyframe ``i == j``, ``T_i_j`` then being
    ``T_w_i``), keyframe ids ``i``, ``j`` (frame indices), the measurement ``T_i_j`` (4, 4) and its ``information``
    (6, 6; right perturbation, ``[rotation, translation]``) as its source stated it; ``source``: for an odometry
    factor, ``"registration"`` or ``"chain"`` (:class:`lrslam.backend.keyframe_link.KeyframeLinkMeasurement`),
    empty otherwise."""

    kind: str
    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray
    source: str = ""


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
        self.n_loops_proposed = self.n_loops_unverified = 0
        self.rejected_loops: list[tuple[int, int]] = []   # removed by the graph's consistency check
        self._noise: GapNoise | None = None                 # the run's measured noise, given at each keyframe
        self.measurements: list[FactorRecord] = []

    def state_dict(self) -> dict:
        """Factors (plain numpy, :meth:`PoseGraph.state`), the loop closer's keyframes, the frontend's chain since
        the last keyframe and the counters, for checkpoints."""
        return {"graph": self.graph.state(), "loop_closer": self.loop_closer.state_dict(),
                "link": self.link.state_dict(), "last": self._last, "n_loops": self.n_loops,
                "n_solves": self.n_solves, "n_loops_disputed": self.n_loops_disputed,
                "n_loops_proposed": self.n_loops_proposed, "n_loops_unverified": self.n_loops_unverified,
                "rejected_loops": list(self.rejected_loops),
                "measurements": [vars(m).copy() for m in self.measurements]}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output."""
        self.graph = type(self.graph).from_state(self.graph.cfg, state["graph"])
        self.loop_closer.load_state_dict(state["loop_closer"])
        self.link.load_state_dict(state["link"])
        self._last = state["last"]
        self.n_loops, self.n_solves = int(state["n_loops"]), int(state["n_solves"])
        self.n_loops_disputed = int(state["n_loops_disputed"])
        self.n_loops_proposed = int(state.get("n_loops_proposed", 0))
        self.n_loops_unverified = int(state.get("n_loops_unverified", 0))
        self.rejected_loops = [(int(i), int(j)) for i, j in state.get("rejected_loops", [])]
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

    @property
    def loop_counts(self) -> dict[str, int]:
        """Loops ``proposed`` (candidates verified by registration), ``unverified`` (rejected by the registration's
        geometry gates), ``disputed`` (by the field's map), ``inconsistent`` (removed by the graph's consistency
        check) and ``kept`` (in the graph)."""
        inconsistent = len(self.rejected_loops)
        added = sum(m.kind == "loop" for m in self.measurements)
        return {"proposed": self.n_loops_proposed, "unverified": self.n_loops_unverified,
                "disputed": self.n_loops_disputed, "inconsistent": inconsistent, "kept": added - inconsistent}

    def on_keyframe(self, frame: Frame, poses: dict[int, np.ndarray], information: np.ndarray | None,
                    noise: GapNoise | None = None, T_field: np.ndarray | None = None) -> Correction:
        """Add keyframe ``frame.index`` (its pose in ``poses``, every keyframe's current ``T_w_c``) with its
        factors; solve when a loop brings a real correction (or at every keyframe); return what to write back.
        ``noise``: the run's measured noise (:meth:`lrslam.backend.frame_fusion.FrameFusion.gap_noise`), which
        calibrates the factors' informations (``calibrate``); None keeps the informations their sources state.
        ``T_field``: the field's own tracked pose of the keyframe (fused mode; recorded as a ``field_pose``
        measurement for :meth:`refine_all`)."""
        self._noise = noise
        if T_field is not None and "field" in self.cfg.factors:
            info = information if information is not None else self._default_info
            self.measurements.append(FactorRecord("field_pose", int(frame.index), int(frame.index),
                                                  np.array(T_field, dtype=np.float64), np.array(info, np.float64)))
        loops, link = self._add_factors(frame, poses, information)
        real = [lc for lc in loops if self._is_correction(lc)]
        if len(loops) > len(real):
            log.info("keyframe %d: %d loop(s) consistent with the trajectory (no solve for them)", frame.index,
                     len(loops) - len(real))
        edges = tuple((lc.i, lc.j) for lc in loops)
        T_link = link.T_registration if link is not None else None
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
        if "odometry" in factors and link is not None and link.trusted:
            self._add("odometry", link.i, link.j, link.T_i_j, link.information, link.source)
        # 3. Loops against earlier keyframes.
        loops = []
        if "loop" in factors:
            verified = self.loop_closer.detect(j, frame, poses)
            self.n_loops_proposed += len(verified) + len(self.loop_closer.rejections)
            self.n_loops_unverified += len(self.loop_closer.rejections)
            loops = self._agreed_by_field(verified, frame, poses)
            for lc in loops:
                self._add("loop", lc.i, lc.j, lc.T_i_j, lc.information)
        self.loop_closer.add_keyframe(j, frame)
        self._last = j
        self.n_loops += len(loops)
        return loops, link

    def _add(self, kind: str, i: int, j: int, T_i_j: np.ndarray, information: np.ndarray, source: str = "") -> None:
        """Add a between factor to the graph and to :attr:`measurements` (``source``: an odometry factor's)."""
        add = {"field": self.graph.add_field_relative, "odometry": self.graph.add_odometry,
               "loop": self.graph.add_loop}[kind]
        add(i, j, T_i_j, information)
        self.measurements.append(FactorRecord(kind, int(i), int(j), np.array(T_i_j, dtype=np.float64),
                                              np.array(information, dtype=np.float64), source))

    def _solve(self, poses: dict[int, np.ndarray], edges: tuple[tuple[int, int], ...]) -> Correction:
        """Step 4: solve from the trajectory's poses, field factors re-stated from them (the graph never reverts
        the mapper's refinements: only loops and the frontend's measurements move poses), informations calibrated
        by the run's noise, inconsistent loops removed; then which keyframes to write and re-map. When every loop
        that brought the solve was removed, nothing is written (the solve had no reason left)."""
        for a, b in zip(list(poses)[:-1], list(poses)[1:]):
            self.graph.set_measurement("field", a, b, inv(poses[a]) @ poses[b])
        noise = self._calibration()
        if noise is not None:
            for f in calibrated(self.measurements, noise, self.cfg.calibrate_registrations):
                self.graph.set_information(f.kind, f.i, f.j, f.information)
        self.n_solves += 1
        before = len(self.rejected_loops)
        solution = self._consistent_solution(self.graph, poses)
        if self.cfg.optimise == "on_loop" and set(self.rejected_loops[before:]) >= set(edges):
            log.info("no loop left after the consistency check: the solve is not applied")
            return Correction(edges=edges)
        return self._correction(poses, solution, edges)

    def refine_all(self, poses: dict[int, np.ndarray], noise: GapNoise | None = None) -> Correction:
        """The final global refinement (``final_refine``): one solve over every keyframe ``poses`` (``{kf:
        T_w_kf}``, the trajectory's) and every measurement, informations calibrated by ``noise`` (as
        :meth:`on_keyframe`), inconsistent loops removed. The field enters as what it is, a pose against the map:
        a prior at its own tracked pose of each keyframe (``field_pose`` records; without them, between factors
        re-stated from ``poses``), the frontend as keyframe-to-keyframe registrations and loops: a smoother over
        the keyframes of what the per-frame fusion filtered forward. Returns what to write and re-map;
        ``Correction.solved`` is False when there was nothing to solve (``final_refine`` off, under two keyframes,
        no measured noise to weigh by, or the field not gated out under ``final_refine_when=field_gated``)."""
        from lrslam.backend.graph import PoseGraph

        self._noise = noise
        ids, cal = self.graph.keyframe_ids, self._calibration(online=False)
        if not self.cfg.final_refine or len(ids) < 2 or any(k not in poses for k in ids) or cal is None:
            return Correction()
        if self.cfg.final_refine_when == "field_gated" and not bool(np.all(cal.field_gated)):
            log.info("final refinement skipped: the field takes a share of the fusion (final_refine_when=field_gated)")
            return Correction()
        graph = PoseGraph(self.graph.cfg.model_copy(update={"optimiser": "lm"})
                          if self.graph.cfg.optimiser == "isam2" else self.graph.cfg)
        graph.add_keyframe(ids[0], poses[ids[0]])
        for k in ids[1:]:
            graph.add_keyframe(k)
        records = calibrated(self.measurements, cal, self.cfg.calibrate_registrations)
        absolute = any(f.kind == "field_pose" for f in records)
        rejected = set(self.rejected_loops)
        for f in records:
            if f.kind == "field_pose" and f.i in poses and self.cfg.final_refine_field:
                graph.add_prior(f.i, f.T_i_j, f.information)
            elif f.kind == "field" and not absolute and self.cfg.final_refine_field:
                graph.add_field_relative(f.i, f.j, inv(poses[f.i]) @ poses[f.j], f.information)
            elif f.kind == "odometry":
                graph.add_odometry(f.i, f.j, f.T_i_j, f.information)
            elif f.kind == "loop" and (f.i, f.j) not in rejected:
                graph.add_loop(f.i, f.j, f.T_i_j, f.information)
        self.n_solves += 1
        return self._correction(poses, self._consistent_solution(graph, poses), ())

    def calibrated_measurements(self) -> list[FactorRecord]:
        """:attr:`measurements` with the informations the graph weighs them by: calibrated by the last noise given
        (``calibrate``, once measured), else as their sources stated them."""
        cal = self._calibration()
        return (calibrated(self.measurements, cal, self.cfg.calibrate_registrations) if cal is not None
                else list(self.measurements))

    def _calibration(self, online: bool = True) -> GapNoise | None:
        """The run's measured noise to weigh the factors by: None before it is measured, and for the online solves
        when ``calibrate`` is off (the final refinement always weighs by it: it has no other weights). With
        ``odometry_factor="chain"`` the odometry factors are weighed by the chain's variance."""
        noise = self._noise
        if self.cfg.odometry_factor == "chain" and noise is not None and noise.chain is not None:
            noise = replace(noise, odometry=noise.chain)   # the odometry factors are the chain
        return noise if (self.cfg.calibrate or not online) and noise is not None and noise.measured else None

    def _consistent_solution(self, graph: PoseGraph, poses: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Solve ``graph`` from ``poses``; while its worst loop's chi2 at the solution exceeds ``loop_max_chi2``,
        remove that loop (counted in :attr:`rejected_loops`) and solve again."""
        while True:
            solution = graph.optimise(poses)
            if self.cfg.loop_max_chi2 <= 0 or graph.cfg.optimiser == "isam2":
                return solution
            chi2 = graph.loop_chi2(solution)
            if not chi2:
                return solution
            i, j, worst = max(chi2, key=lambda c: c[2])
            if worst <= self.cfg.loop_max_chi2:
                return solution
            graph.remove_loop(i, j)
            if (i, j) not in self.rejected_loops:
                self.rejected_loops.append((i, j))
            log.info("loop %d-%d removed: inconsistent with the graph (chi2 %.1f > %.1f at its solution)", i, j,
                     worst, self.cfg.loop_max_chi2)

    def _correction(self, poses: dict[int, np.ndarray], solution: dict[int, np.ndarray],
                    edges: tuple[tuple[int, int], ...]) -> Correction:
        """Which keyframes of ``solution`` to write (moved more than ``write_min_shift_*``) and to re-map (the
        most-moved, beyond ``remap_min_shift_m``)."""
        c = self.cfg
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
