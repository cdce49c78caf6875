"""How much to smooth: runs' trajectories as tracked (``trajectory_unsmoothed.txt``) smoothed again offline under
several models of the tracking error, with the ATE against ground truth for each (evaluation only: nothing here
changes a run).

Models (camera centres only; rotations are left as tracked, as the run's own smoothing does):

- ``tracked``: as tracked, no smoothing;
- ``shipped``: :func:`lrslam.backend.smoother.smooth_trajectory` at its defaults (white error, the weight from the
  second differences at spacings 1 and 3); equals the run's ``trajectory.txt`` when the run smoothed with them;
- ``lam=L``: a Whittaker smoother at a fixed weight ``L`` (``--lams``), the same on every sequence;
- ``drift``: the error as white noise plus a random walk that starts at zero at the first frame, the motion white
  noise on acceleration; the three variances fitted by non-negative least squares to the mean squared second
  differences at spacings 1-4 (``6 v_w + 2 k v_r + k^4 v_a``), the motion's MAP estimate solved as a sparse
  saddle point (:func:`drift_smooth`), each weight clipped at 100 (docs/BENCHMARKS.md section 28: tried, not
  kept);
- ``ar1``: the error as a first-order autoregression (``e_i = rho e_(i-1) + noise``, ``rho`` from a grid
  0-0.95 by the best fit of ``2 v (3 - 4 rho^k + rho^2k) + k^4 v_a`` at spacings 1-6), the motion's MAP estimate
  ``(L^T L + lam D^T D) m = L^T L x`` (:func:`ar1_solve`; section 28).

Per run: the ATE RMSE (cm) under each model, and the mean over the runs given.

Usage::

    python benchmarks/smoothing.py SEQUENCE RUN [RUN ...] [--lams 1,10,100,300]

``SEQUENCE`` is the dataset folder the runs ran on; each run's stride comes from its ``config.yaml``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from lrslam.backend.smoother import SmoothingConfig

_CAP = SmoothingConfig().max_lambda   # each error term's largest weight: the shipped smoothing's
_MIN_FRAMES = 15        # second differences at spacings 1-6 (the ar1 fit) need more than 12 frames


def _structure_fit(x: np.ndarray, t: np.ndarray, spacing: int, columns) -> tuple[np.ndarray, float]:
    """Non-negative least squares of the mean squared second differences of ``x`` (N, d) at spacings ``k = 1 ..
    spacing`` (per component) against ``columns(k)`` ((spacing,) -> (spacing, m) design), on relative residuals:
    ``(coefficients (m,), residual norm)``."""
    from scipy.optimize import nnls

    from lrslam.backend.smoother import _second_differences

    k = np.arange(1, spacing + 1, dtype=np.float64)
    v = np.array([np.mean(_second_differences(x, t, int(ki)) ** 2) for ki in k])
    w = 1.0 / np.maximum(v, 1e-300)
    coef, res = nnls(columns(k) * w[:, None], v * w)
    return coef, float(res)


def _ratio(a: float, b: float) -> float:
    """``a / b`` clipped at the cap (``b`` may be 0: no motion measured)."""
    return float(min(a / max(b, 1e-300), _CAP))


def drift_fit(x: np.ndarray, t: np.ndarray, spacing: int = 4) -> tuple[float, float, float]:
    """``(v_w, v_r, v_a)``: white, random-walk step and motion variances per component (module docstring)."""
    coef, _ = _structure_fit(x, t, spacing, lambda k: np.stack([np.full_like(k, 6.0), 2.0 * k, k ** 4], 1))
    return float(coef[0]), float(coef[1]), float(coef[2])


def drift_smooth(x: np.ndarray, t: np.ndarray, lam: float, q: float) -> np.ndarray:
    """The motion ``m`` (N, d) minimising ``|x - m - r|^2 / v_w + |D1 r|^2 / v_r + |D2 m|^2 / v_a`` with ``m_0 =
    x_0``, ``r_0 = 0``, ``lam = v_w / v_a``, ``q = v_r / v_a > 0``; ``D1`` first differences (steps scaled to
    their time), ``D2`` the smoother's second derivative. Solved as ``[[D2'D2, 0, I], [0, D1'D1 / q, I],
    [I, I, -lam I]] [m; r; u] = [0; 0; x - x_0]``, regular also at ``lam = 0``."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    from lrslam.backend.smoother import second_difference_matrix

    n = len(x)
    dt = np.diff(t)
    s = 1.0 / np.sqrt(dt / np.median(dt))
    d1 = sp.diags([s, -s[1:]], [0, -1], format="csc")          # rows s_i (r_(i+1) - r_i), r_0 = 0
    d2 = second_difference_matrix(t)[:, 1:]
    eye = sp.identity(n - 1, format="csc")
    A = sp.bmat([[d2.T @ d2, None, eye], [None, (d1.T @ d1) / q, eye], [eye, eye, -lam * eye]]).tocsc()
    rhs = np.zeros((3 * (n - 1), x.shape[1]))
    rhs[2 * (n - 1):] = x[1:] - x[0]
    out = x.copy()
    out[1:] = np.asarray(spl.splu(A).solve(rhs))[: n - 1] + x[0]
    return out


def ar1_fit(x: np.ndarray, t: np.ndarray, spacing: int = 6) -> tuple[float, float]:
    """``(rho, lam)`` of the ``ar1`` model for ``x`` (N, d): the grid ``rho`` whose structure function fits best,
    ``lam = v_noise / v_a`` (``v_noise = v (1 - rho^2)``, the autoregression's innovation), clipped at 100; 0 where
    no error is measured."""
    best = None
    for rho in np.linspace(0.0, 0.95, 20):
        coef, res = _structure_fit(x, t, spacing,
                                   lambda k, rho=rho: np.stack([2 * (3 - 4 * rho ** k + rho ** (2 * k)), k ** 4], 1))
        if best is None or res < best[0]:
            best = (res, float(rho), coef[0], coef[1])
    _, rho, var_e, var_a = best
    return rho, (_ratio(var_e * (1 - rho ** 2), var_a) if var_e > 0 else 0.0)


def ar1_solve(x: np.ndarray, t: np.ndarray, rho: float, lam: float) -> np.ndarray:
    """The motion ``m`` (N, d) minimising ``|L (x - m)|^2 + lam |D2 m|^2`` with ``m_0 = x_0``: ``L`` the
    autoregression's whitening (rows ``e_i - rho e_(i-1)``, ``e_0 = 0``; even spacing assumed), ``D2`` the
    smoother's second derivative; ``(L^T L + lam D2^T D2) m = L^T L x``. ``rho = 0`` is the Whittaker smoother."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    from lrslam.backend.smoother import second_difference_matrix

    if lam <= 0:
        return x.copy()
    n = len(x)
    L = sp.diags([np.ones(n - 1), -rho * np.ones(n - 2)], [0, -1], format="csc")
    Q = (L.T @ L).tocsc()
    d2 = second_difference_matrix(t)[:, 1:]
    out = x.copy()
    out[1:] = spl.splu((Q + lam * (d2.T @ d2)).tocsc()).solve(Q @ (x[1:] - x[0])) + x[0]
    return out


def _models(lams: list[float]):
    from lrslam.backend.smoother import smooth_trajectory, whittaker

    def centres(fn):
        def apply(P, t):
            out = P.copy()
            out[:, :3, 3] = fn(P[:, :3, 3], t)
            return out
        return apply

    def drift(x, t):
        vw, vr, va = drift_fit(x, t)
        lam, q = _ratio(vw, va), _ratio(vr, va)
        return drift_smooth(x, t, lam, q) if q > 0 else whittaker(x, lam, t, keep_first=True)

    models = {"tracked": lambda P, t: P, "shipped": lambda P, t: smooth_trajectory(P, t).poses}
    for lam in lams:
        models[f"lam={lam:g}"] = centres(lambda x, t, lam=lam: whittaker(x, lam, t, keep_first=True))
    models["drift"] = centres(drift)
    models["ar1"] = centres(lambda x, t: ar1_solve(x, t, *ar1_fit(x, t)))
    return models


def _lams(text: str) -> list[float]:
    """``--lams`` ("1,10,100") -> weights; ValueError naming the option when one is not a finite number >= 0."""
    vals = []
    for v in text.split(","):
        if v.strip():
            lam = float(v)
            if not (np.isfinite(lam) and lam >= 0):
                raise ValueError(v)
            vals.append(lam)
    return vals


def _load_run(run: Path, sequence: str, sequences: dict):
    """``(timestamps (N,), poses (N, 4, 4), Sequence)`` of a run folder, the sequence opened with the run's own
    reader options (cached per options). Raises ValueError / TypeError / AttributeError / yaml.YAMLError /
    InputError on bad input (the caller names the run)."""
    import yaml

    from lrslam.datasets import ReaderOptions, open_sequence
    from lrslam.evaluation.ate import read_trajectory

    traj, cfg_path = run / "trajectory_unsmoothed.txt", run / "config.yaml"
    if not traj.is_file() or not cfg_path.is_file():
        raise ValueError("no trajectory_unsmoothed.txt / config.yaml (a run folder of lrslam run)")
    ds = yaml.safe_load(cfg_path.read_text())["dataset"]
    options = dict(ds.get("options") or {})
    key = (ds.get("reader"), repr(sorted(options.items())))
    if key not in sequences:
        sequences[key] = open_sequence(sequence, key[0], ReaderOptions(**options))
    t, P = read_trajectory(traj)
    if len(t) < _MIN_FRAMES or not np.all(np.diff(t) > 0):
        raise ValueError(f"{traj}: needs at least {_MIN_FRAMES} poses at increasing times")
    return t, P, sequences[key]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", help="the dataset folder the runs ran on")
    ap.add_argument("runs", nargs="+", help="run folders holding trajectory_unsmoothed.txt and config.yaml")
    ap.add_argument("--lams", default="1,10,100,300", help="fixed Whittaker weights to compare")
    args = ap.parse_args(argv)

    import yaml

    from lrslam.errors import InputError
    from lrslam.evaluation.ate import compute_run_ate

    try:
        models = _models(_lams(args.lams))
    except ValueError as e:
        print(f"error: --lams: {e} is not a finite number >= 0", file=sys.stderr)
        return 2
    rows: list[tuple[str, list[float]]] = []
    sequences: dict = {}
    for run in map(Path, args.runs):
        try:
            t, P, seq = _load_run(run, args.sequence, sequences)
            ate = [compute_run_ate(t, fn(P, t), seq) for fn in models.values()]
        except (InputError, ValueError, TypeError, AttributeError, KeyError, yaml.YAMLError) as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            print(f"error: {run}: {msg}", file=sys.stderr)
            return 2
        if any(a is None for a in ate):
            print(f"error: {args.sequence}: no ground truth", file=sys.stderr)
            return 2
        rows.append((str(run), [a.rmse_cm for a in ate]))
    width = max(len(r) for r, _ in rows)
    print(f"{'run':<{width}}  " + "  ".join(f"{m:>8}" for m in models))
    for run, vals in rows:
        print(f"{run:<{width}}  " + "  ".join(f"{v:8.3f}" for v in vals))
    if len(rows) > 1:
        mean = np.mean([v for _, v in rows], axis=0)
        print(f"{'mean':<{width}}  " + "  ".join(f"{v:8.3f}" for v in mean))
    return 0


if __name__ == "__main__":
    sys.exit(main())
