"""Hand-held-like camera trajectories inside a synthetic room.

World frame (see :mod:`lrslam.datasets.synth.scene`): metres, z up, floor at the bottom of the bound.
Poses are camera-to-world ``T_w_c`` (N, 4, 4) float64 with OpenCV camera axes (x right, y down, z forward,
:mod:`lrslam.camera`).

Every trajectory is a smooth curve ``s -> (position, yaw, pitch, roll)`` that is re-timed so that each frame
moves by one "step" of the combined motion metric ``sqrt(((dt / trans_step)^2 + (dr / rot_step)^2) / 2)``
(dt: translation in metres, dr: rotation angle in degrees). With the defaults (1 cm, 1 deg per frame at 30 Hz)
a frame that both moves and turns moves about 1 cm and turns about 1 deg; pure translation gives ~1.4 cm,
pure rotation ~1.4 deg. The camera stays inside :func:`camera_region`, which the scene generator keeps at
least 0.5 m away from every wall and object.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.spatial.transform import Rotation

from lrslam.errors import InputError

__all__ = ["TRAJECTORIES", "camera_region", "make_trajectory", "look_rotation", "motion_per_frame"]

TRAJECTORIES = ("circle", "helix", "random_walk", "loop", "orbit")

# A curve maps a parameter array (M,) to positions (M, 3) and yaw/pitch/roll (M, 3) in radians.
Curve = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def camera_region(bound: np.ndarray) -> np.ndarray:
    """Box (3, 2) in metres where cameras may go, derived from a scene bound (3, 2).

    x, y: centred, half-width ``clip(ext / 2 - 1.3, 0.25, 0.2 ext)`` for a bound extent ``ext`` (0.8 x 0.3 m
    half-widths in the 4 x 3 m ``room``), which leaves a >= 0.45 m band along the walls of rooms >= 2.5 m for
    furniture;
    z: from 40 % to 65 % of the bound height (about 1.0-1.65 m above the floor in a 2.5 m room).
    :func:`lrslam.datasets.synth.scene.make_scene` places objects so that they stay at least 0.5 m away from
    this box (low objects may sit below it).
    """
    bound = np.asarray(bound, dtype=np.float64).reshape(3, 2)
    lo, ext = bound[:, 0], bound[:, 1] - bound[:, 0]
    c = lo + 0.5 * ext
    half = np.minimum(np.maximum(0.5 * ext[:2] - 1.3, 0.25), 0.2 * ext[:2])
    return np.array([[c[0] - half[0], c[0] + half[0]],
                     [c[1] - half[1], c[1] + half[1]],
                     [lo[2] + 0.40 * ext[2], lo[2] + 0.65 * ext[2]]])


def look_rotation(yaw_pitch_roll: np.ndarray) -> np.ndarray:
    """Camera-to-world rotations (M, 3, 3) (OpenCV axes) from yaw/pitch/roll (M, 3) radians.

    The optical axis (camera z) points along ``(cos p cos y, cos p sin y, sin p)`` in the z-up world frame
    (pitch > 0 looks up); camera x stays horizontal before the roll, which then turns the image about z.
    """
    ypr = np.atleast_2d(np.asarray(yaw_pitch_roll, dtype=np.float64))
    y, p, r = ypr[:, 0], ypr[:, 1], ypr[:, 2]
    z = np.stack([np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), np.sin(p)], axis=-1)
    x = np.stack([np.sin(y), -np.cos(y), np.zeros_like(y)], axis=-1)  # = normalise(z x up), horizontal
    yv = np.cross(z, x)
    R0 = np.stack([x, yv, z], axis=-1)
    return R0 @ Rotation.from_rotvec(np.outer(r, [0.0, 0.0, 1.0])).as_matrix()


def _poses(pos: np.ndarray, ypr: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(pos), 1, 1))
    T[:, :3, :3] = look_rotation(ypr)
    T[:, :3, 3] = pos
    return T


def motion_per_frame(T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame motion of a trajectory (N, 4, 4): (translation (N-1,) metres, rotation (N-1,) degrees)."""
    T = np.asarray(T_w_c, dtype=np.float64)
    dt = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=-1)
    Rrel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
    cos = np.clip((np.trace(Rrel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return dt, np.degrees(np.arccos(cos))


def _metric(curve: Curve, s: np.ndarray, trans_step: float, rot_step_deg: float) -> np.ndarray:
    """Cumulative motion metric (in frames) along a dense parameter grid s (M,)."""
    dt, dr = motion_per_frame(_poses(*curve(s)))
    step = np.sqrt(((dt / trans_step) ** 2 + (dr / rot_step_deg) ** 2) / 2.0)
    return np.concatenate([[0.0], np.cumsum(step)])


def _retime(curve: Curve, s_max: float, n_frames: int, step: float, trans_step: float, rot_step_deg: float,
            dense: int) -> np.ndarray:
    """Sample frames i * step (i < n_frames) of the metric along curve(s), s in [0, s_max]."""
    s = np.linspace(0.0, s_max, dense)
    m = _metric(curve, s, trans_step, rot_step_deg)
    s_frames = np.interp(np.arange(n_frames) * step, m, s)
    return _poses(*curve(s_frames))


def _circle(region: np.ndarray, rng: np.random.Generator, helix: bool, yaw_rate: float | None = None) -> Curve:
    """circle / helix; ``yaw_rate``: an orbit whose heading turns ``yaw_rate`` times as fast as its position
    angle (starting inwards), so that it travels far per degree turned (a translation-heavy fast camera)."""
    c = region.mean(axis=1)
    half = 0.5 * (region[:, 1] - region[:, 0])
    rx, ry = 0.85 * half[0], 0.85 * half[1]
    theta0 = rng.uniform(0, 2 * np.pi)
    pitch = np.radians(rng.uniform(-20.0, -10.0))
    hz = 0.8 * half[2]

    def curve(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        th = theta0 + s
        z = np.full_like(s, c[2]) if not helix else c[2] - hz * np.cos(0.5 * s)  # up in one turn, down in the next
        pos = np.stack([c[0] + rx * np.cos(th), c[1] + ry * np.sin(th), z], axis=-1)
        # circle: look inwards across the room; helix: look outwards at the nearer walls and furniture
        yaw = th + (np.pi if not helix else 0.0) if yaw_rate is None else theta0 + np.pi + yaw_rate * s
        ypr = np.stack([yaw, np.full_like(s, pitch), np.zeros_like(s)], axis=-1)
        return pos, ypr

    return curve


def _random_walk(region: np.ndarray, rng: np.random.Generator, n_knots: int) -> Curve:
    """Monotone (PCHIP) interpolation of random-walk knots: C1, never leaves the knots' box (no overshoot).

    Consecutive knots are 0.15-0.45 m and 15-45 deg of yaw apart (about the 1 cm : 1 deg ratio of the nominal
    speed), so neither translation nor rotation dominates for long."""
    inner = region.mean(axis=1)[:, None] + 0.9 * (region - region.mean(axis=1)[:, None])
    pos = np.empty((n_knots, 3))
    pos[0] = rng.uniform(inner[:, 0], inner[:, 1])
    for k in range(1, n_knots):
        d = rng.normal(size=3) * [1.0, 1.0, 0.5]
        step = rng.uniform(0.15, 0.45) * d / np.linalg.norm(d)
        nxt = pos[k - 1] + step
        nxt = np.where(nxt > inner[:, 1], 2 * inner[:, 1] - nxt, nxt)  # reflect at the region's faces
        nxt = np.where(nxt < inner[:, 0], 2 * inner[:, 0] - nxt, nxt)
        pos[k] = np.clip(nxt, inner[:, 0], inner[:, 1])
    turns = np.radians(rng.uniform(15.0, 45.0, n_knots)) * rng.choice([-1.0, 1.0], n_knots)
    yaw = rng.uniform(0, 2 * np.pi) + np.cumsum(turns)
    pitch = np.radians(rng.uniform(-35.0, 5.0, n_knots))
    roll = np.radians(rng.normal(0.0, 4.0, n_knots))
    knots = np.arange(n_knots, dtype=np.float64)
    fp = PchipInterpolator(knots, pos, axis=0)
    fa = PchipInterpolator(knots, np.stack([yaw, pitch, roll], axis=-1), axis=0)
    return lambda s: (fp(s), fa(s))


def _loop(region: np.ndarray, rng: np.random.Generator, scale: float) -> Curve:
    """One closed lap: an ellipse with a vertical figure-eight wobble; the view direction sways and returns."""
    c = region.mean(axis=1)
    half = 0.5 * (region[:, 1] - region[:, 0])
    # The lap starts at the region centre: x - c in [-2a, 2a], so a, b use half the region's half-widths.
    a, b, h = 0.425 * half[0] * scale, 0.425 * half[1] * scale, 0.5 * half[2] * scale
    yaw0 = rng.uniform(0, 2 * np.pi)
    amp_yaw, amp_pitch = np.radians(60.0) * scale, np.radians(10.0) * scale
    pitch0 = np.radians(rng.uniform(-20.0, -5.0))
    ph = rng.uniform(0, 2 * np.pi)

    def curve(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos = np.stack([c[0] + a * np.cos(s + ph) - a * np.cos(ph), c[1] + b * np.sin(s + ph) - b * np.sin(ph),
                        c[2] + h * np.sin(2 * s)], axis=-1)
        ypr = np.stack([yaw0 + amp_yaw * np.sin(s), pitch0 + amp_pitch * np.sin(2 * s),
                        np.radians(3.0) * scale * np.sin(s)], axis=-1)
        return pos, ypr

    return curve


def make_trajectory(kind: str, n_frames: int, scene_bound: np.ndarray, seed: int = 0,
                    trans_step: float = 0.01, rot_step_deg: float = 1.0) -> np.ndarray:
    """Camera-to-world poses ``T_w_c`` (n_frames, 4, 4) float64, OpenCV camera axes, inside the room.

    Args:
        kind: ``circle`` (ellipse around the room centre at constant height, looking inwards across the room),
            ``helix`` (same ellipse, looking outwards at the walls while the height goes up over one turn and
            down over the next), ``random_walk`` (smooth hand-held wandering through random knots with random
            yaw/pitch/roll), ``loop`` (one closed lap sized so that n_frames fit at the nominal speed -- or
            several laps when the room is too small -- whose last frame is one step before the first), ``orbit``
            (the circle's ellipse, heading turning at 0.4x the rate of the position angle: with
            ``trans_step=0.06, rot_step_deg=2.4`` a fast, translation-heavy camera).
        n_frames: number of poses (>= 2).
        scene_bound: (3, 2) metres, the scene's ``bound``; cameras stay in :func:`camera_region` of it.
        seed: random seed (start angle, knots, ...); same inputs give the same poses.
        trans_step, rot_step_deg: nominal motion per frame (metres, degrees), see the module docstring.
    """
    if kind not in TRAJECTORIES:
        raise InputError(f"unknown trajectory {kind!r}; choose one of {', '.join(TRAJECTORIES)}")
    if n_frames < 2:
        raise InputError(f"a trajectory needs at least 2 frames, got {n_frames}")
    if trans_step <= 0 or rot_step_deg <= 0:
        raise InputError("trajectory steps must be positive")
    region = camera_region(scene_bound)
    steps = (trans_step, rot_step_deg)

    def rng() -> np.random.Generator:  # a fresh, identical stream for every candidate curve
        return np.random.default_rng([int(seed), TRAJECTORIES.index(kind)])

    if kind in ("circle", "helix", "orbit"):
        # orbit: heading turns at 0.4x the position angle: about 2.5 cm per degree in the 4 x 3 m room
        curve = _circle(region, rng(), helix=kind == "helix", yaw_rate=0.4 if kind == "orbit" else None)
        s_max = 2 * np.pi
        while (total := _metric(curve, np.linspace(0.0, s_max, 2000), *steps)[-1]) < n_frames:
            s_max *= 1.2 * n_frames / total
        return _retime(curve, s_max, n_frames, 1.0, *steps, dense=max(4000, 20 * n_frames))
    if kind == "random_walk":
        n_knots = 4
        while True:
            curve = _random_walk(region, rng(), n_knots)
            total = _metric(curve, np.linspace(0.0, n_knots - 1, 200 * n_knots), *steps)[-1]
            if total >= n_frames - 1:
                return _retime(curve, n_knots - 1, n_frames, 1.0, *steps, dense=max(2000, 20 * n_frames))
            n_knots = int(np.ceil(n_knots * 1.5 * (n_frames - 1) / max(total, 1.0))) + 1
    # loop: choose the lap size so that one lap takes n_frames steps (3 fixed-point updates: nearly linear)
    scale, laps = 1.0, 1
    full = _metric(_loop(region, rng(), 1.0), np.linspace(0.0, 2 * np.pi, 1441), *steps)[-1]
    if full >= n_frames:
        scale = n_frames / full
        for _ in range(3):
            lap = _metric(_loop(region, rng(), scale), np.linspace(0.0, 2 * np.pi, 1441), *steps)[-1]
            scale *= n_frames / lap
    else:
        laps = max(1, int(round(n_frames / full)))
    curve = _loop(region, rng(), scale)
    dense = max(2000, 20 * n_frames)
    total = _metric(curve, np.linspace(0.0, 2 * np.pi * laps, dense), *steps)[-1]
    return _retime(curve, 2 * np.pi * laps, n_frames, total / n_frames, *steps, dense=dense)
