"""``benchmarks/smoothing.py``: the drift model's saddle-point solve against the dense normal equations of its MAP
problem, the AR(1) model's solve against its normal equations and the Whittaker smoother (exact), and its
bad-input exits."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from smoothing import ar1_solve, drift_smooth, main  # noqa: E402
from test_smoother import _divided_differences  # noqa: E402

from lrslam.backend.smoother import whittaker  # noqa: E402


def test_drift_smooth_solves_its_map_problem():
    rng = np.random.default_rng(0)
    n = 40
    t = np.cumsum(rng.uniform(0.02, 0.05, n))
    x = rng.normal(size=(n, 3))
    D2 = _divided_differences(t)[:, 1:]                                       # m_0 = x_0: its column drops out
    dt = np.diff(t)
    D1 = np.zeros((n - 1, n - 1))                                 # r_0 = 0: increments r_(i+1) - r_i
    for i in range(n - 1):
        D1[i, i] = 1.0
        if i:
            D1[i, i - 1] = -1.0
    D1 /= np.sqrt(dt / np.median(dt))[:, None]
    y = x[1:] - x[0]
    eye = np.eye(n - 1)
    for lam, q in ((3.0, 20.0), (0.5, 2.0)):
        # d/dm and d/dr of |y - m - r|^2 / lam + |D1 r|^2 / q + |D2 m|^2 (v_a = 1)
        A = np.block([[eye / lam + D2.T @ D2, eye / lam], [eye / lam, eye / lam + D1.T @ D1 / q]])
        m = np.linalg.solve(A, np.vstack([y / lam, y / lam]))[: n - 1]
        out = drift_smooth(x, t, lam, q)
        assert np.array_equal(out[0], x[0])
        assert np.allclose(out[1:] - x[0], m, atol=1e-9)
    # no white part: r = x - m exactly, (D2'D2 + D1'D1 / q) m = D1'D1 y / q
    m0 = np.linalg.solve(D2.T @ D2 + D1.T @ D1 / 5.0, D1.T @ D1 @ y / 5.0)
    assert np.allclose(drift_smooth(x, t, 0.0, 5.0)[1:] - x[0], m0, atol=1e-9)
    line = np.outer(t - t[0], [0.3, -0.2, 0.05]) + 1.0          # constant velocity: returned as it is
    assert np.allclose(drift_smooth(line, t, 3.0, 20.0), line, atol=1e-10)


def test_ar1_solve_is_the_map_estimate_and_whittaker_without_correlation():
    rng = np.random.default_rng(1)
    n = 50
    t = np.arange(n) / 30.0
    x = rng.normal(size=(n, 3))
    assert np.allclose(ar1_solve(x, t, 0.0, 7.0), whittaker(x, 7.0, t, keep_first=True), atol=1e-10)
    rho, lam = 0.6, 4.0
    L = np.eye(n - 1) - rho * np.eye(n - 1, k=-1)                # e_i - rho e_(i-1), e_0 = 0
    D2 = _divided_differences(t)[:, 1:]
    y = x[1:] - x[0]
    m = np.linalg.solve(L.T @ L + lam * D2.T @ D2, L.T @ L @ y)
    out = ar1_solve(x, t, rho, lam)
    assert np.array_equal(out[0], x[0]) and np.allclose(out[1:] - x[0], m, atol=1e-10)


def test_bad_input_exits_2_with_one_line(tmp_path, capsys):
    assert main([str(tmp_path), str(tmp_path)]) == 2                 # not a run folder
    assert "trajectory_unsmoothed.txt" in capsys.readouterr().err
    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory_unsmoothed.txt").write_text("0 0 0 0 0 0 0 1\n")
    for cfg in ("dataset: [unclosed", "- a list", "dataset:\n  reader: tum\n  options: {stride: x}"):
        (run / "config.yaml").write_text(cfg)
        assert main([str(tmp_path), str(run)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {run}") and err.count("\n") == 1
    assert main([str(tmp_path), str(run), "--lams", "1,nan"]) == 2
    assert "--lams" in capsys.readouterr().err
