"""The minimal data a registration needs from one RGB-D frame, plus the checks and measures every method shares.

:class:`RGBDView` holds ``rgb``, ``depth`` and ``K`` (nothing else: no ground truth, no timestamps) and caches the
derived data the registrations build (Open3D images, point clouds, a KISS-ICP voxel map), so a reference frame
is preprocessed once however many frames register against it.

Shared measures, identical for every method so that the gates mean the same thing:

- :func:`view_problem`: why a view cannot be registered (no depth, featureless), or None;
- :func:`assess_alignment`: projective fitness, inlier RMSE (metres) and normalised 6x6 information of a
  relative pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from lrslam.camera import backproject_depth, block_intrinsics, project_points, strided_intrinsics, transform_points
from lrslam.errors import InputError
from lrslam.frame import DepthSized
from lrslam.geometry import hat

__all__ = [
    "FrameLike", "RGBDView", "AlignmentQuality", "as_view", "valid_mask",
    "view_problem", "normal_spread", "intensity_std", "normal_map", "assess_alignment",
]


class FrameLike(Protocol):
    """Anything with ``rgb (H, W, 3) uint8``, ``depth (H, W) float32`` metres and ``K (3, 3)``, e.g.
    :class:`lrslam.frame.Frame`."""

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray


@dataclass
class RGBDView(DepthSized):
    """One RGB-D image pair for registration.

    Attributes:
        rgb: (H, W, 3) uint8, RGB order.
        depth: (H, W) float32 metres, z-depth; 0 = invalid (values outside ``[depth_min, depth_max]`` of the
            config in use are ignored by the registrations).
        K: (3, 3) float64 pinhole intrinsics (OpenCV convention, :mod:`lrslam.camera`).
        cache: derived data keyed by what built it (Open3D objects); never part of any result.
    """

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    cache: dict[Any, Any] = field(default_factory=dict, repr=False, compare=False)

    def cached(self, key: Any, build) -> Any:
        """``cache[key]``, built with ``build()`` on first use."""
        if key not in self.cache:
            self.cache[key] = build()
        return self.cache[key]

    def state(self) -> dict[str, np.ndarray]:
        """The images and intrinsics as numpy arrays (the cache is rebuilt on use), for checkpoints."""
        return {"rgb": self.rgb.copy(), "depth": self.depth.copy(), "K": self.K.copy()}

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> "RGBDView":
        """Rebuild a view from :meth:`state`."""
        return cls(np.ascontiguousarray(state["rgb"], dtype=np.uint8),
                   np.ascontiguousarray(state["depth"], dtype=np.float32), np.asarray(state["K"], dtype=np.float64))

    def downsampled(self, factor: int, max_depth_spread: float = 0.05) -> "RGBDView":
        """A copy ``factor`` times smaller per side: colour and depth averaged over each ``factor`` x ``factor``
        block (depth over its valid pixels; a block spanning a depth edge, valid depths more than
        ``max_depth_spread`` m apart, keeps its central sample instead of mixing the two surfaces), intrinsics
        rescaled about the block centres (:func:`block_intrinsics`)."""
        if factor <= 1:
            return RGBDView(self.rgb, self.depth, self.K)
        import cv2

        h, w = self.height // factor, self.width // factor
        rgb = cv2.resize(self.rgb[:h * factor, :w * factor], (w, h), interpolation=cv2.INTER_AREA)
        blocks = self.depth[:h * factor, :w * factor].reshape(h, factor, w, factor).astype(np.float64)
        valid = blocks > 0
        n = valid.sum(axis=(1, 3))
        mean = np.where(n > 0, blocks.sum(axis=(1, 3)) / np.maximum(n, 1), 0.0)
        spread = np.where(valid, blocks, -np.inf).max(axis=(1, 3)) - np.where(valid, blocks, np.inf).min(axis=(1, 3))
        centre = blocks[:, factor // 2, :, factor // 2]
        depth = np.where((n > 0) & (spread > max_depth_spread), centre, mean).astype(np.float32)
        return RGBDView(rgb, depth, block_intrinsics(self.K, factor))


def as_view(frame: FrameLike | RGBDView) -> RGBDView:
    """Wrap a frame-like object (or return an :class:`RGBDView` as is). Shapes and dtypes are checked here, so
    a wrong input fails with one line naming the problem (:class:`~lrslam.errors.InputError`)."""
    if isinstance(frame, RGBDView):
        return frame
    rgb, depth, K = np.asarray(frame.rgb), np.asarray(frame.depth), np.asarray(frame.K, dtype=np.float64)
    if depth.ndim != 2:
        raise InputError(f"depth must be (H, W) metres, got shape {depth.shape}")
    if rgb.shape != depth.shape + (3,):
        raise InputError(f"rgb must be (H, W, 3) matching depth {depth.shape}, got {rgb.shape}")
    if K.shape != (3, 3):
        raise InputError(f"K must be 3x3, got {K.shape}")
    if rgb.dtype != np.uint8:
        rgb = np.clip(rgb * (255.0 if rgb.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    depth = np.nan_to_num(depth.astype(np.float32, copy=False), nan=0.0, posinf=0.0, neginf=0.0)
    return RGBDView(np.ascontiguousarray(rgb), np.ascontiguousarray(depth), K)


def valid_mask(view: RGBDView, depth_min: float, depth_max: float) -> np.ndarray:
    """(H, W) bool: pixels whose depth lies in ``[depth_min, depth_max]`` metres."""
    return (view.depth >= depth_min) & (view.depth <= depth_max)


def intensity_std(view: RGBDView, mask: np.ndarray | None = None) -> float:
    """Standard deviation of the grey level (0..1) over ``mask`` (default: all pixels)."""
    grey = view.rgb.astype(np.float32).mean(axis=2) / 255.0
    vals = grey[mask] if mask is not None else grey
    return float(vals.std()) if vals.size else 0.0


def normal_spread(view: RGBDView, depth_min: float, depth_max: float, stride: int = 4,
                  max_jump: float = 0.1) -> float:
    """How well the surface normals constrain a translation: the smallest eigenvalue of ``mean(n n^T)`` over
    surface normals from finite differences of the back-projected depth (sub-sampled by ``stride``). 0 for a
    single plane (translation along it is unobservable to point-to-plane ICP), up to 1/3 for normals spread
    evenly in all directions. ``max_jump`` (m) drops differences across depth discontinuities. Cached."""

    def build() -> float:
        d = view.depth[::stride, ::stride].astype(np.float64)
        P = backproject_depth(d, strided_intrinsics(view.K, stride))
        ok = (d >= depth_min) & (d <= depth_max)
        dx, dy = P[:-1, 1:] - P[:-1, :-1], P[1:, :-1] - P[:-1, :-1]
        good = ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1]
        good &= (np.abs(dx[..., 2]) < max_jump) & (np.abs(dy[..., 2]) < max_jump)
        n = np.cross(dx[good], dy[good])
        norm = np.linalg.norm(n, axis=1)
        n = n[norm > 0] / norm[norm > 0, None]
        if len(n) < 10:
            return 0.0
        return float(np.linalg.eigvalsh(n.T @ n / len(n))[0])

    return view.cached(("spread", depth_min, depth_max, stride, max_jump), build)


def view_problem(view: RGBDView, *, depth_min: float, depth_max: float, min_valid_fraction: float,
                 min_intensity_std: float, min_normal_spread: float, uses_colour: bool) -> str | None:
    """Why ``view`` cannot be registered, or None when it can.

    - fewer than ``min_valid_fraction`` pixels with depth in range -> "no valid depth ...";
    - geometry degenerate (:func:`normal_spread` < ``min_normal_spread``, e.g. one flat wall) and, for methods
      that use colour (``uses_colour``), also no texture (:func:`intensity_std` < ``min_intensity_std``) ->
      "featureless ...". Results are cached on the view.
    """
    key = ("problem", depth_min, depth_max, min_valid_fraction, min_intensity_std, min_normal_spread, uses_colour)

    def build() -> str | None:
        mask = valid_mask(view, depth_min, depth_max)
        frac = float(mask.mean())
        if frac < min_valid_fraction:
            return f"no valid depth ({100 * frac:.1f}% of pixels in [{depth_min}, {depth_max}] m)"
        spread = normal_spread(view, depth_min, depth_max)
        if spread >= min_normal_spread:
            return None
        if not uses_colour:
            return f"degenerate geometry (normal spread {spread:.3g} < {min_normal_spread})"
        texture = intensity_std(view, mask)
        if texture < min_intensity_std:
            return (f"featureless frame (intensity std {texture:.3g} < {min_intensity_std}, "
                    f"normal spread {spread:.3g} < {min_normal_spread})")
        return None

    return view.cached(key, build)


@dataclass(frozen=True)
class AlignmentQuality:
    """Projective alignment measures of a relative pose ``T_tgt_src``.

    Attributes:
        fitness: inliers / valid source pixels (0..1).
        inlier_rmse: RMS point-to-plane distance (m) of the inlier correspondences (inf when there is none).
        n_inliers: number of inlier correspondences (on the sub-sampled grid).
        information: (6, 6) normalised information of ``T_tgt_src`` for a right perturbation
            ``T_tgt_src exp(xi)``, ``xi = [rotation (rad), translation (m)]`` in the source frame (GTSAM's
            ``BetweenFactor(tgt, src)`` convention); see :func:`assess_alignment`. Zeros without inliers.
    """

    fitness: float
    inlier_rmse: float
    n_inliers: int
    information: np.ndarray


def normal_map(view: RGBDView, depth_min: float, depth_max: float, max_jump: float = 0.1) -> np.ndarray:
    """(H, W, 3) float32 unit surface normals (camera frame) from central differences of the back-projected depth;
    zeros where a neighbour is invalid or across depth jumps larger than ``max_jump`` (m). Cached on the view."""

    def build() -> np.ndarray:
        P = backproject_depth(view.depth, view.K)
        ok = (view.depth >= depth_min) & (view.depth <= depth_max)
        dx, dy = P[1:-1, 2:] - P[1:-1, :-2], P[2:, 1:-1] - P[:-2, 1:-1]
        good = ok[1:-1, 2:] & ok[1:-1, :-2] & ok[2:, 1:-1] & ok[:-2, 1:-1] & ok[1:-1, 1:-1]
        good &= (np.abs(dx[..., 2]) < max_jump) & (np.abs(dy[..., 2]) < max_jump)
        n = np.cross(dx, dy)
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        good &= norm[..., 0] > 0
        out = np.zeros(P.shape, dtype=np.float32)
        out[1:-1, 1:-1] = np.where(good[..., None], n / np.where(norm > 0, norm, 1.0), 0.0)
        return out

    return view.cached(("normals", depth_min, depth_max, max_jump), build)


def assess_alignment(source: RGBDView, target: RGBDView, T_tgt_src: np.ndarray, *, max_distance: float,
                     depth_min: float, depth_max: float, sigma_m: float, stride: int = 2) -> AlignmentQuality:
    """Fitness, inlier RMSE and information of a relative pose, by projective data association (as RGB-D
    odometry does). The same measure for every registration method, so the gates mean the same thing.

    Source pixels (every ``stride``-th, depth in ``[depth_min, depth_max]`` m) are back-projected to ``p_k``,
    moved into the target camera by ``T_tgt_src`` (4x4), projected to the nearest target pixel and compared
    with the target's back-projected point ``r_k`` there. Inliers: ``|r_k - T p_k| < max_distance`` (m). The
    RMSE is the point-to-plane distance (target normal, :func:`normal_map`), so it does not include the
    nearest-pixel quantisation (about half a pixel footprint, ~6 mm at 3 m and 320x240).

    Information: ``H = sum_k G_k^T G_k`` with ``G_k = [-[p_k]x, I]`` (the Jacobian of ``T exp(xi) p_k`` up to
    the rotation R, which leaves ``G^T G`` unchanged) is the point-to-point information with unit noise. It is
    the same as Open3D's ``compute_odometry_information_matrix`` moved from its left perturbation to a right
    one (``Ad_T^T H_o3d Ad_T``, checked in the tests). Returned normalised: ``H / N / sigma_m^2``:

    - dividing by N removes the dependence on image size and correspondence count (neighbouring pixels are not
      independent measurements, so ``H`` itself would be wildly over-confident);
    - ``sigma_m`` (m) is the unit noise: the translation standard deviation is then ``sigma_m`` in every
      direction (the translation block of ``H / N`` is the identity) and the rotation one about
      ``sigma_m / (typical scene distance)`` rad, shaped by the scene geometry.
    """
    none = AlignmentQuality(0.0, float("inf"), 0, np.zeros((6, 6)))
    d = source.depth[::stride, ::stride]
    ok = (d >= depth_min) & (d <= depth_max)
    n_valid = int(ok.sum())
    if n_valid == 0:
        return none
    p = backproject_depth(d, strided_intrinsics(source.K, stride))[ok]
    q = transform_points(T_tgt_src, p)
    uv, z = project_points(q, target.K)
    with np.errstate(invalid="ignore"):
        u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    inside = (z > 0) & (u >= 0) & (u < target.width) & (v >= 0) & (v < target.height)
    p, q, u, v = p[inside], q[inside], u[inside].astype(int), v[inside].astype(int)
    d_t = target.depth[v, u].astype(np.float64)
    r = np.stack([(u - target.K[0, 2]) / target.K[0, 0] * d_t, (v - target.K[1, 2]) / target.K[1, 1] * d_t,
                  d_t], axis=1)
    inl = (d_t >= depth_min) & (d_t <= depth_max) & (np.linalg.norm(r - q, axis=1) < max_distance)
    n = int(inl.sum())
    if n == 0:
        return none
    normals = normal_map(target, depth_min, depth_max)[v[inl], u[inl]]
    has_normal = np.any(normals != 0, axis=1)
    plane_dist = np.einsum("ij,ij->i", r[inl] - q[inl], normals)[has_normal]
    rmse = float(np.sqrt(np.mean(plane_dist ** 2))) if plane_dist.size else float("inf")
    p = p[inl]
    # sum_k [-[p]x, I]^T [-[p]x, I] in closed form.
    S = p.T @ p
    s = p.sum(axis=0)
    sx = hat(s)
    H = np.zeros((6, 6))
    H[:3, :3] = np.trace(S) * np.eye(3) - S
    H[:3, 3:] = sx
    H[3:, :3] = sx.T
    H[3:, 3:] = n * np.eye(3)
    return AlignmentQuality(n / n_valid, rmse, n, H / n / sigma_m ** 2)
