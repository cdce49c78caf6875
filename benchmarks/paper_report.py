"""Markdown for ``benchmarks/paper.py``: every measured number next to the paper's, and where they disagree."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _m(x: float) -> str:
    return f"{x / 1e6:.3f} M"


def _f(x, nd: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{nd}f}"


def write_report(path: Path, size, res: dict, timings: dict, paper_t1: dict, paper_t4: dict) -> Path:
    """Write ``path`` (RESULTS.md) from the section results of ``benchmarks/paper.py``; returns the path."""
    L = [f"# LRSLAM, reproduced side by side ({size.name} settings)", "",
         f"Written by `python benchmarks/paper.py{'' if size.name == 'full' else ' --' + size.name}` on this "
         f"machine in {timings['total']:.0f} s. Every number below was produced by that run, except the columns "
         "marked *paper* (LRSLAM, ECCV 2024). Runs use field mode (constant-velocity seed, field tracking and "
         "mapping, the paper's setting) with CPU-sized settings: synthetic sequences of "
         f"{size.frames} frames at 320x240, real excerpts of {size.real_frames} frames (`tum-cpu`, `7scenes-cpu` "
         f"presets), config overrides `{' '.join(size.overrides) or 'none'}`. The paper's runs are GPU-sized "
         "(Replica 8 x 2000 tracking, ScanNet 30 x 2000, TUM 200 x 5000, whole sequences, an A100).", ""]
    # 1. Table 1
    t1 = res["table1"]
    L += ["## 1. Table 1: parameters and frame time", "",
          "Parameters are exact closed forms of ESLAM's per-scene bounds (room0, scene0000, fr1/desk), identical "
          "on any machine; *total* includes the two decoders, as the paper's totals do.", "",
          "| dataset | method | f_g | f_a | total | paper f_g / f_a / total |", "|---|---|---|---|---|---|"]
    agree = True
    for (ds, r), (g, a, tot) in t1["counts"].items():
        p = paper_t1[ds][r]
        same = (round(g / 1e6, 2), round(a / 1e6, 2), round(tot / 1e6, 2)) == p[:3]
        agree &= same
        L.append(f"| {ds} | {'LRSLAM' if r == 'lrslam' else 'ESLAM'} | {_m(g)} | {_m(a)} | {_m(tot)} | "
                 f"{p[0]:.2f} / {p[1]:.2f} / {p[2]:.2f} M {'(agrees)' if same else '(**differs**)'} |")
    ratios = t1["ratios"]
    paper_r = {ds: paper_t1[ds]["lrslam"][3] / paper_t1[ds]["eslam"][3] for ds in paper_t1}
    L += ["", "All parameter counts agree with the paper to its rounding." if agree else
          "Some parameter counts differ from the paper (marked).", "",
          f"Whole-run frame time, CP-SA / tri-plane, alternated {len(ratios)} times in one process on the synthetic "
          f"sequence: ratios {', '.join(f'{x:.3f}' for x in ratios)} (median {np.median(ratios):.3f}; CP-SA "
          f"{np.median(t1['fpt']['lrslam']):.3f} s/frame, tri-plane {np.median(t1['fpt']['eslam']):.3f} s/frame). "
          "Paper (A100): " + ", ".join(f"{ds} {v:.3f}" for ds, v in paper_r.items()) + ".", ""]
    faster = np.median(ratios) < 1.0
    L += [("CP-SA is faster per frame here, as in the paper. " if faster else
           "CP-SA is **not** faster per frame here, unlike the paper. ") +
          "On a CPU the ratio reflects our kernels (materialised Six-axis planes, numba samplers) and the small "
          "synthetic scene (tri-plane memory traffic is small at this bound), not the paper's GPU; the paper's "
          "gain also grows with scene size (Replica 0.96 vs TUM 0.27).", ""]
    # 2. Memory growth
    mg = res["memory"]
    L += ["## 2. Memory growth: parameters vs scene side", "", "![memory](paper_memory.png)", "",
          "| L (m) | " + " | ".join(mg["rows"]) + " |", "|---|" + "---|" * len(mg["rows"])]
    for i, side in enumerate(mg["sides"]):
        L.append(f"| {side:g} | " + " | ".join(_m(v[i]) for v in mg["rows"].values()) + " |")
    L += ["", "Fitted log-log slopes (largest three sides): " +
          ", ".join(f"{k} {v:.2f}" for k, v in mg["slopes"].items()) +
          ". Paper: tri-plane O(L^2), CP / SA / CP-SA O(L). " +
          ("Agrees." if mg["slopes"]["tri-plane"] > 1.8 and all(v < 1.2 for k, v in mg["slopes"].items()
                                                               if k != "tri-plane") else "**Disagrees.**"), ""]
    # 3. Ablation
    ab = res["ablation"]
    L += ["## 3. Ablation [A]-[D] and tri-plane", "", "![ablation](paper_ablation.png)", "",
          f"ATE RMSE (cm) over {size.seeds} seeds per variant (`field.seed`), field mode.", "",
          "| sequence | variant | ATE RMSE mean | min | max | parameters | s/frame |", "|---|---|---|---|---|---|---|"]
    for label, by_v in ab.items():
        for v, runs in by_v.items():
            a = np.array([x["ate"] for x in runs], dtype=float)
            L.append(f"| {label} | {v} | {_f(np.nanmean(a))} | {_f(np.nanmin(a))} | {_f(np.nanmax(a))} | "
                     f"{_m(runs[0]['params']) if runs[0]['params'] else '-'} | "
                     f"{np.mean([x['fpt'] for x in runs]):.3f} |")
    L += ["", "Parameters: f_g + f_a of the run's bound (decoders excluded). Paper (ScanNet, Fig. ablation): SA and "
          "CP take \"4-6 % and 8-12 % less\" parameters than tri-plane. Read as *fewer* that contradicts its own "
          "Table 1 (CP-SA has 87-90 % fewer); read as *of* tri-plane it matches the closed forms at ScanNet "
          "bounds (scene0000: CP-CP 0.71 M = 4.0 %, SA-SA 1.42 M = 8.0 % of 17.63 M) with CP and SA swapped. "
          "On our smaller bounds the ratios are larger (planes grow as L^2, lines as L). The paper also reports "
          "the largest ATE variance for CP-CP [A]; our excerpts are short, so differences between variants "
          "smaller than the seed spread in the table are not significant.", ""]
    # 4. Noise
    nz = res["noise"]
    keys = ("depth_l1_cm", "accuracy_cm", "completion_cm", "completion_ratio", "ate_mean_cm", "ate_rmse_cm")
    L += ["## 4. Depth-noise robustness (Table 4 bottom)", "",
          f"Synthetic room loop, {size.noise_frames} frames, depth + N(0, 0.05^2) m; mesh metrics with the ESLAM "
          f"protocol (`lrslam eval mesh` default) at {size.eval_points:,} points and {size.depth_views} NICE-SLAM "
          "depth views (paper: Replica room0, 450,000 points, 1000 views); the mesh is evaluated in the GT world "
          "(`initial_pose: gt`, `evaluate_run_mesh`).", "",
          "| method | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    for r in ("eslam", "lrslam"):
        name = "ESLAM (tri-plane)" if r == "eslam" else "LRSLAM (CP-SA)"
        L.append(f"| {name} | " + " | ".join(_f(nz[r].get(k)) for k in keys) + " |")
        L.append(f"| *paper* {name} | " + " | ".join(_f(paper_t4[r][k]) for k in keys) + " |")
    def wins(k):
        a, b = nz["lrslam"].get(k), nz["eslam"].get(k)
        return a is not None and b is not None and (a > b if k == "completion_ratio" else a < b)

    better = [k for k in keys if wins(k)]
    L += ["", f"CP-SA beats tri-plane here on: {', '.join(better) or 'none'} (paper: all but completion ratio). "
          "Absolute values differ from the paper's: another scene (synthetic room, not Replica room0), "
          "a few frames instead of 2000, CPU-sized iterations.", ""]
    # 5. Convergence
    cv = res["convergence"]
    L += ["## 5. Convergence", "", "![convergence](paper_convergence.png)", "",
          "First-frame mapping of the synthetic room (pose fixed); loss of the last iteration and depth L1 (cm) of a "
          "quarter-resolution render of that frame after k iterations (one fresh, seeded field per k).", "",
          "| variant | " + " | ".join(f"k={c['iters']}" for c in next(iter(cv.values()))) + " |",
          "|---|" + "---|" * len(next(iter(cv.values())))]
    for v, curve in cv.items():
        L.append(f"| {v} | " + " | ".join(f"{c['loss']:.4f} / {c['depth_l1_cm']:.1f}" for c in curve) + " |")
    first = {v: c[0]["depth_l1_cm"] for v, c in cv.items()}
    cp_fast = first["[A] CP-CP"] <= min(first["[B] SA-SA"], first["tri-plane (ESLAM)"])
    L += ["", "(loss / depth L1 cm.) Paper: CP converges faster. " +
          ("Here CP-CP has the lowest depth L1 after the fewest iterations: agrees." if cp_fast else
           "Here CP-CP does **not** have the lowest depth L1 after the fewest iterations: disagrees on this scene "
           "and settings (a single first frame; the paper's claim is about whole runs)."), "",
          "## Timings", "", ", ".join(f"{k} {v:.0f} s" for k, v in timings.items()), ""]
    path.write_text("\n".join(L))
    return path
