"""Keyframe pose graph (GTSAM): prior on the first keyframe, between factors from the frontend odometry, from
field-refined poses and from verified loop closures (robust kernel), optimised in batch (Levenberg-Marquardt),
incrementally (iSAM2), or with graduated non-convexity (GNC) deciding which loops are outliers.

Nodes are camera poses ``T_w_c`` (4x4) keyed by keyframe id; a factor ``(i, j, T_i_j, information)`` says that
keyframe j's camera sits at ``T_i_j`` in keyframe i's camera, with information for a right perturbation
``T_i_j exp(xi)``, ``xi = [rotation (rad), translation (m)]`` (see :mod:`lrslam.backend.conversions`).

The graph holds **no pose estimates**: it keeps the keyframe ids and the factor records (plain numpy,
:meth:`PoseGraph.state`, so it can be checkpointed and rebuilt with :meth:`PoseGraph.from_state`), and every
:meth:`PoseGraph.optimise` starts from the poses the caller (the pipeline's trajectory, their one owner) passes
in, mapper refinements included. A factor's measurement can be replaced (:meth:`PoseGraph.set_measurement`),
e.g. to re-state a field factor from the current poses. With ``optimiser="isam2"`` GTSAM keeps its own
linearisation point between calls (new keyframes start from the given poses): use ``lm`` (default) or ``gnc``
for a solve that always starts from the owner's poses.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import Field

from lrslam.backend.conversions import gaussian_from_information, key, pose_to_gtsam, robust_noise, values_to_dict
from lrslam.config import StrictModel
from lrslam.errors import InputError
from lrslam.geometry import between_residual, diagonal_information, inv

__all__ = ["GraphConfig", "PoseGraph"]

log = logging.getLogger(__name__)

FactorKind = Literal["prior", "odometry", "field", "loop"]


class GraphConfig(StrictModel):
    """Pose-graph settings. Angles in degrees, distances in metres; robust parameters in sigma units."""

    # Loops are wrapped in this M-estimator. Huber (convex) keeps correct loops after large drift, and bounds a
    # wrong loop's pull; that bound only protects the trajectory when the odometry is stiff (its information
    # as confident as the frontend's). Cauchy / DCS also ignore *correct* loops whose residual starts large.
    # With realistic (soft) odometry information use optimiser="gnc" instead, which decides loop inliers by a
    # chi-square test (robust_kernel and robust_sequential are then not used). ATE in cm on the 40-keyframe
    # drifting circle of tests/test_backend_graph.py: stiff odometry (0.5 deg, 1 cm): no loop 14.1, correct
    # loop 2.3 (Huber; Cauchy 13.6, DCS 14.1), wrong loop 13.5 (Huber) vs 29.3 (none); soft odometry (2 deg,
    # 3 cm): wrong loop 29.9 with Huber (as with none), GNC: no loop 22.8, correct 3.1, wrong 22.8.
    robust_kernel: Literal["huber", "cauchy", "dcs", "none"] = "huber"
    robust_parameter: float = Field(1.345, gt=0, description="kernel width in whitened (sigma) units")
    robust_sequential: bool = Field(False, description="also apply the kernel to odometry and field factors")
    prior_sigma_rotation: float = Field(1e-3, gt=0)
    prior_sigma_translation: float = Field(1e-5, gt=0)
    field_sigma_rotation: float = Field(0.5, gt=0, description="default sigma of field-relative factors")
    field_sigma_translation: float = Field(0.01, gt=0)
    optimiser: Literal["lm", "isam2", "gnc"] = "lm"
    max_iterations: int = Field(100, gt=0)
    relative_error_tol: float = Field(1e-10, ge=0)
    absolute_error_tol: float = Field(1e-10, ge=0)
    isam2_relinearize_threshold: float = Field(1e-3, gt=0)
    isam2_extra_updates: int = Field(5, ge=0, description="extra iSAM2 iterations per optimise() call")
    gnc_inlier_threshold: float = Field(
        0.0, ge=0, description="GNC: inlier cost threshold of a loop (0 = GTSAM's default)")


@dataclass
class _Factor:
    kind: FactorKind
    i: int
    j: int  # == i for priors
    T: np.ndarray  # T_i_j, or T_w_i for priors
    information: np.ndarray


class PoseGraph:
    """Keyframe pose graph. See module docstring for conventions."""

    def __init__(self, cfg: GraphConfig):
        self.cfg = cfg
        self._ids: list[int] = []
        self._factors: list[_Factor] = []
        self._constrained: set[int] = set()  # keyframes that appear in a factor
        self._isam = None
        self._isam_keys: set[int] = set()
        self._isam_pending = 0  # index into _factors of the first factor not yet given to iSAM2
        if cfg.optimiser == "isam2":
            self._reset_isam()

    # -- building --------------------------------------------------------------------------------------------
    @property
    def keyframe_ids(self) -> list[int]:
        return list(self._ids)

    @property
    def n_loops(self) -> int:
        return sum(f.kind == "loop" for f in self._factors)

    @property
    def n_factors(self) -> int:
        return len(self._factors)

    def add_keyframe(self, kf_id: int, T_w_c_prior: np.ndarray | None = None) -> None:
        """Add node ``kf_id``. The first keyframe needs ``T_w_c_prior`` (4x4): a prior there (``prior_sigma_*``)
        fixes the gauge. Later keyframes ignore it (their poses come with each :meth:`optimise`)."""
        kf_id = int(kf_id)
        if kf_id in self._ids:
            raise InputError(f"pose graph: keyframe {kf_id} added twice")
        if not self._ids and T_w_c_prior is None:
            raise InputError(f"pose graph: the first keyframe ({kf_id}) needs a prior pose")
        self._ids.append(kf_id)
        if len(self._ids) == 1:
            self.add_prior(kf_id, T_w_c_prior)

    def add_prior(self, kf_id: int, T_w_c: np.ndarray, information: np.ndarray | None = None) -> None:
        """Prior factor on keyframe ``kf_id`` (default information from ``prior_sigma_*``)."""
        if information is None:
            information = diagonal_information(np.radians(self.cfg.prior_sigma_rotation),
                                            self.cfg.prior_sigma_translation)
        self._add("prior", kf_id, kf_id, T_w_c, information)

    def add_odometry(self, i: int, j: int, T_i_j: np.ndarray, information: np.ndarray) -> None:
        """Between factor from the frontend odometry: keyframe j's pose in keyframe i (4x4) with its 6x6
        information."""
        self._add("odometry", i, j, T_i_j, information)

    def add_field_relative(self, i: int, j: int, T_i_j: np.ndarray, information: np.ndarray | None = None,
                           sigmas: tuple[float, float] | None = None) -> None:
        """Between factor from field-refined poses (``T_i_j = inv(T_w_i) @ T_w_j``). Information: given, or
        from ``sigmas = (rotation deg, translation m)``, or the config's ``field_sigma_*``."""
        if information is None:
            rot, trans = sigmas if sigmas is not None else (self.cfg.field_sigma_rotation,
                                                            self.cfg.field_sigma_translation)
            information = diagonal_information(np.radians(rot), trans)
        self._add("field", i, j, T_i_j, information)

    def add_loop(self, i: int, j: int, T_i_j: np.ndarray, information: np.ndarray) -> None:
        """Loop-closure between factor, wrapped in the configured robust kernel."""
        self._add("loop", i, j, T_i_j, information)

    def set_measurement(self, kind: FactorKind, i: int, j: int, T_i_j: np.ndarray,
                        information: np.ndarray | None = None) -> bool:
        """Replace the measurement (and optionally the information) of the existing ``kind`` factor ``i``-``j``.
        Returns False when there is no such factor. Not with ``isam2`` (its factors are already inside GTSAM)."""
        if self.cfg.optimiser == "isam2":
            raise InputError("pose graph: set_measurement needs optimiser lm or gnc")
        for f in self._factors:
            if f.kind == kind and (f.i, f.j) == (int(i), int(j)):
                f.T = self._check(kind, i, j, T_i_j, f.information if information is None else information)[0]
                if information is not None:
                    f.information = np.asarray(information, dtype=np.float64).copy()
                return True
        return False

    def set_information(self, kind: FactorKind, i: int, j: int, information: np.ndarray) -> bool:
        """Replace the information (6, 6) of the existing ``kind`` factor ``i``-``j`` (e.g. calibrated from the
        run's measured noise). Returns False when there is no such factor. Not with ``isam2``."""
        for f in self._factors:
            if f.kind == kind and (f.i, f.j) == (int(i), int(j)):
                return self.set_measurement(kind, i, j, f.T, information)
        return False

    def remove_loop(self, i: int, j: int) -> bool:
        """Remove the loop factor ``i``-``j`` (rejected by the graph's consistency check). Returns False when there
        is none. Not with ``isam2``."""
        if self.cfg.optimiser == "isam2":
            raise InputError("pose graph: remove_loop needs optimiser lm or gnc")
        n = len(self._factors)
        self._factors = [f for f in self._factors if not (f.kind == "loop" and (f.i, f.j) == (int(i), int(j)))]
        self._constrained = {k for f in self._factors for k in (f.i, f.j)}
        return len(self._factors) < n

    def loop_chi2(self, poses: dict[int, np.ndarray]) -> list[tuple[int, int, float]]:
        """``[(i, j, chi2)]`` of every loop factor at ``poses`` (``{kf_id: T_w_c}``): its normalised squared residual
        ``e^T Lambda e`` (:func:`lrslam.geometry.between_residual`; chi-square with 6 degrees of freedom for a loop
        consistent with the rest of the graph)."""
        return [(f.i, f.j, between_residual(f.T, f.information, inv(poses[f.i]) @ poses[f.j])[1])
                for f in self._factors if f.kind == "loop" and f.i in poses and f.j in poses]

    def _check(self, kind: FactorKind, i: int, j: int, T: np.ndarray, information: np.ndarray):
        what = f"pose graph: {kind} factor {i}-{j}"
        for k in {i, j}:
            if k not in self._ids:
                raise InputError(f"{what}: keyframe {k} was never added")
        if kind != "prior" and i == j:
            raise InputError(f"{what}: a between factor needs two different keyframes")
        pose_to_gtsam(T, what)
        gaussian_from_information(information, f"{what}: information")
        return np.asarray(T, dtype=np.float64).copy(), np.asarray(information, dtype=np.float64).copy()

    def _add(self, kind: FactorKind, i: int, j: int, T: np.ndarray, information: np.ndarray) -> None:
        i, j = int(i), int(j)
        T, information = self._check(kind, i, j, T, information)
        self._factors.append(_Factor(kind, i, j, T, information))
        self._constrained.update((i, j))

    def _gtsam_factor(self, f: _Factor):
        import gtsam

        pose = pose_to_gtsam(f.T)
        noise = gaussian_from_information(f.information)
        robust = f.kind == "loop" or (self.cfg.robust_sequential and f.kind in ("odometry", "field"))
        if robust and self.cfg.optimiser != "gnc":  # GNC applies its own robust loss to the loops
            noise = robust_noise(noise, self.cfg.robust_kernel, self.cfg.robust_parameter)
        if f.kind == "prior":
            return gtsam.PriorFactorPose3(key(f.i), pose, noise)
        return gtsam.BetweenFactorPose3(key(f.i), key(f.j), pose, noise)

    def _gtsam_graph(self):
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for f in self._factors:
            graph.add(self._gtsam_factor(f))
        return graph

    # -- optimisation ----------------------------------------------------------------------------------------
    def optimise(self, poses: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Optimise from ``poses`` (``{kf_id: T_w_c}``, every keyframe of the graph) and return the optimised
        ``{kf_id: T_w_c}`` for every keyframe (keyframes without any factor keep the given pose). Degenerate
        graphs (no keyframe, no between factor) return the given poses, with a log line; a failed solve (e.g. a
        keyframe cluster with no path to the prior) is logged and returns them unchanged too."""
        start = self._start(poses)
        if not self._ids:
            log.info("pose graph: no keyframes, nothing to optimise")
            return {}
        if not any(f.kind != "prior" for f in self._factors):
            log.info("pose graph: %d keyframe(s) and no between factor, nothing to optimise", len(self._ids))
            return start
        try:
            if self.cfg.optimiser == "isam2":
                result = self._optimise_isam2(start)
            else:
                result = self._optimise_batch(start)
        except RuntimeError as e:
            log.error("pose graph: optimisation failed (%s); keeping the given poses",
                      str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__)
            if self._isam is not None:
                self._reset_isam()  # its state is unknown after a failed update: rebuild on the next call
            return start
        return start | result

    def _start(self, poses: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        missing = [i for i in self._ids if i not in poses]
        if missing:
            raise InputError(f"pose graph: no pose given for keyframe(s) {missing}")
        out = {}
        for i in self._ids:
            pose_to_gtsam(poses[i], f"pose graph: pose of keyframe {i}")
            out[i] = np.asarray(poses[i], dtype=np.float64).copy()
        return out

    @staticmethod
    def _values(poses: dict[int, np.ndarray], ids) -> Any:
        import gtsam

        values = gtsam.Values()
        for i in ids:
            values.insert(key(i), pose_to_gtsam(poses[i]))
        return values

    def _optimise_batch(self, start: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        import gtsam

        ids = [i for i in self._ids if i in self._constrained]
        initial = self._values(start, ids)
        graph = self._gtsam_graph()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.cfg.max_iterations)
        params.setRelativeErrorTol(self.cfg.relative_error_tol)
        params.setAbsoluteErrorTol(self.cfg.absolute_error_tol)
        if self.cfg.optimiser == "gnc":
            gnc = gtsam.GncLMParams(params)
            # Every factor but the loops is trusted; GNC decides which loops are inliers.
            gnc.setKnownInliers([n for n, f in enumerate(self._factors) if f.kind != "loop"])
            if self.cfg.gnc_inlier_threshold > 0:
                gnc.setInlierCostThreshold(self.cfg.gnc_inlier_threshold)
            optimizer = gtsam.GncLMOptimizer(graph, initial, gnc)
            result = optimizer.optimize()
            weights = np.asarray(optimizer.getWeights())
            n_out = int(sum(w < 0.5 for w, f in zip(weights, self._factors) if f.kind == "loop"))
            if n_out:
                log.info("pose graph: GNC rejected %d of %d loop factors", n_out, self.n_loops)
        else:
            result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
        return values_to_dict(result, ids)

    def _reset_isam(self) -> None:
        import gtsam

        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.cfg.isam2_relinearize_threshold)
        params.relinearizeSkip = 1  # check relinearisation at every update (GTSAM's default is 10)
        self._isam = gtsam.ISAM2(params)
        self._isam_keys = set()
        self._isam_pending = 0

    def _optimise_isam2(self, start: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        import gtsam

        new_factors = gtsam.NonlinearFactorGraph()
        for n in range(self._isam_pending, len(self._factors)):
            new_factors.add(self._gtsam_factor(self._factors[n]))
        new_ids = sorted({k for f in self._factors[self._isam_pending:] for k in (f.i, f.j)} - self._isam_keys)
        self._isam.update(new_factors, self._values(start, new_ids))
        for _ in range(self.cfg.isam2_extra_updates):
            self._isam.update()
        self._isam_pending = len(self._factors)
        self._isam_keys.update(new_ids)
        return values_to_dict(self._isam.calculateEstimate(), sorted(self._isam_keys))

    # -- queries ---------------------------------------------------------------------------------------------
    def marginal_covariance(self, kf_id: int, poses: dict[int, np.ndarray]) -> np.ndarray:
        """6x6 marginal covariance of keyframe ``kf_id`` (tangent ``[rotation, translation]``, right
        perturbation) at ``poses`` (``{kf_id: T_w_c}``, e.g. the result of :meth:`optimise`)."""
        import gtsam

        kf_id = int(kf_id)
        if kf_id not in self._ids:
            raise InputError(f"pose graph: unknown keyframe {kf_id}")
        if kf_id not in self._constrained:
            raise InputError(f"pose graph: keyframe {kf_id} is not constrained by any factor")
        if self._isam is not None and kf_id in self._isam_keys:
            return np.asarray(self._isam.marginalCovariance(key(kf_id)))
        ids = [i for i in self._ids if i in self._constrained]
        marginals = gtsam.Marginals(self._gtsam_graph(), self._values(self._start(poses), ids))
        return np.asarray(marginals.marginalCovariance(key(kf_id)))

    # -- state -----------------------------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Plain-data snapshot (keyframe ids and factor records) for checkpoints; see :meth:`from_state`."""
        return {
            "ids": list(self._ids),
            "factors": [{"kind": f.kind, "i": f.i, "j": f.j, "T": f.T.copy(), "information": f.information.copy()}
                        for f in self._factors],
        }

    @classmethod
    def from_state(cls, cfg: GraphConfig, state: dict[str, Any]) -> "PoseGraph":
        """Rebuild a graph from :meth:`state` (the first keyframe's prior is one of the stored factors)."""
        graph = cls(cfg)
        graph._ids = [int(i) for i in state["ids"]]
        for f in state["factors"]:
            graph._add(f["kind"], f["i"], f["j"], f["T"], f["information"])
        return graph
