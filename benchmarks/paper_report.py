"""Markdown for ``benchmarks/paper.py``: every measured number next to the paper's, and where they disagree."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _m(x: float) -> str:
    return f"{x / 1e6:.3f} M"


def _f(x, nd: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{nd}f}"


CONVERGED_CM = 20.0   # depth L1 (cm) that counts as "the first frame's geometry is there"


def _iters_to(curve: list[dict], threshold_cm: float) -> int | None:
    """First checkpoint (iterations) whose depth L1 is below ``threshold_cm``; None when none is."""
    return next((c["iters"] for c in curve if c["depth_l1_cm"] < threshold_cm), None)


def write_report(path: Path, size, res: dict, timings: dict, paper_t1: dict, paper_t4: dict) -> Path:
    """Write ``path`` (RESULTS.md) from the section results of ``benchmarks/paper.py``; returns the path."""
    cmd = "python benchmarks/paper.py" + ("" if size.name == "full" else " --" + size.name)
    load = res.get("load", {})
    L = [f"# LRSLAM, reproduced side by side ({size.name} settings)", "",
         (f"Written by `{cmd}` on this machine in {timings['total'] / 60:.1f} minutes. Every number below was "
         "produced by that run, except the columns marked *paper* (LRSLAM, ECCV 2024). The prose around the "
         "tables is the script's template: its verdicts (agrees / **disagrees**) are computed from the numbers."), ""]
    if load:
        L += [(f"Machine: {load['cpus']} CPU cores, torch {load['torch_threads']} thread(s); load average "
              f"{load['start']:.1f} at the start and {load['end']:.1f} at the end (other processes shared the "
              "cores: frame times are comparable within this document, not as absolute speeds)."), ""]
    L += [("**Settings (CPU-sized; the paper's are GPU-sized: Replica 8 x 2000 tracking, ScanNet 30 x 2000, TUM "
          "200 x 5000 iterations x pixels, whole sequences, an A100).** Field mode throughout, the paper's "
          "pipeline: constant-velocity seed, field tracking, field mapping every `schedule.map_every` frames. "
          f"Synthetic room loop of {size.frames} frames at 320x240 (`synthetic` preset); real excerpts: the first "
          f"{size.real_frames} frames of `../shared/data` TUM fr1/rpy (`tum-cpu`) and 7-Scenes redkitchen "
          f"(`7scenes-cpu`), 320x240; config overrides on every run: `{' '.join(size.overrides) or 'none'}` "
          "(the presets' own tracking / mapping iterations would take ~5x longer; on 2 shared cores even the full "
          "version uses these)."), "",
          ("**Tracking seed.** The field-mode seed is ESLAM's: linear extrapolation of translation and quaternion "
          "from the last two poses (`schedule.velocity_model: linear`, the default; `se3` repeats the last "
          "relative motion on SE(3) instead). **ATE**: RMSE / mean after SE(3) Umeyama alignment, each estimated "
          "pose paired with the nearest ground-truth sample (`compute_run_ate`, the association of `lrslam eval "
          "ate` and evo), in cm. **Mesh metrics**: the ESLAM / NICE-SLAM protocol, the default of `lrslam eval "
          "mesh` (any-vertex frustum culling over all frames, ICP refinement, NICE-SLAM depth L1 from random views "
          "in the GT bounding box)."), ""]
    # 1. Table 1
    t1 = res["table1"]
    L += ["## 1. Table 1: parameters and frame time", "",
          ("Parameters are exact closed forms of ESLAM's per-scene bounds (room0, scene0000, fr1/desk), identical "
          "on any machine; *total* includes the two decoders, as the paper's totals do."), "",
          "| dataset | method | f_g | f_a | total | paper f_g / f_a / total |", "|---|---|---|---|---|---|"]
    agree = True
    for (ds, r), (g, a, tot) in t1["counts"].items():
        p = paper_t1[ds][r]
        same = (round(g / 1e6, 2), round(a / 1e6, 2), round(tot / 1e6, 2)) == p[:3]
        agree &= same
        L.append(f"| {ds} | {'LRSLAM' if r == 'lrslam' else 'ESLAM'} | {_m(g)} | {_m(a)} | {_m(tot)} | "
                 f"{p[0]:.2f} / {p[1]:.2f} / {p[2]:.2f} M {'(agrees)' if same else '(**differs**)'} |")
    ratios, cpu_ratios = t1["ratios"], t1["cpu_ratios"]
    paper_r = {ds: paper_t1[ds]["lrslam"][3] / paper_t1[ds]["eslam"][3] for ds in paper_t1}
    L += ["", "All parameter counts agree with the paper to its rounding." if agree else
          "Some parameter counts differ from the paper (marked).", "",
          (f"Whole-run frame time, CP-SA / tri-plane, the two alternated {len(ratios)} times in one process on the "
           f"synthetic sequence ({size.frames} frames). CPU time of the process (1 thread: what a run takes alone "
           f"on this CPU): ratios {', '.join(f'{x:.3f}' for x in cpu_ratios)} (median {np.median(cpu_ratios):.3f}; "
           f"CP-SA {np.median(t1['cpu_fpt']['lrslam']):.3f} s/frame, tri-plane "
           f"{np.median(t1['cpu_fpt']['eslam']):.3f} s/frame). Wall clock, which also counts what other processes "
           f"on the shared cores took: ratios {', '.join(f'{x:.3f}' for x in ratios)} (CP-SA "
           f"{np.median(t1['fpt']['lrslam']):.3f}, tri-plane {np.median(t1['fpt']['eslam']):.3f} s/frame). "
           "Paper (A100, FPT): ") + ", ".join(f"{ds} {v:.3f}" for ds, v in paper_r.items()) + ".", ""]
    faster = np.median(cpu_ratios) < 1.0
    L += [("CP-SA is faster per frame here (CPU time), as in the paper. " if faster else
           "CP-SA is **not** faster per frame here (CPU time), unlike the paper. ") +
          "On a CPU the ratio reflects our kernels (Six-axis planes materialised from their factors each step, "
          "numba samplers) and the small synthetic bound (tri-plane memory traffic is small there), not the "
          "paper's GPU, where the plane lookups of ESLAM dominate; the paper's gain also grows with scene size "
          "(Replica 0.96 vs TUM 0.27). The per-sequence CPU ratios of section 3 show the same on the real "
          "excerpts' larger bounds.", ""]
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
          (f"ATE RMSE (cm) over {size.seeds} seeds per variant (`field.seed`), field mode, on the synthetic room "
          "loop and the real excerpts (the paper: two ScanNet scenes, five runs each, whole sequences; ScanNet is "
          "not available here)."), "",
          "| sequence | variant | ATE RMSE mean | min | max | parameters | CPU s/frame | wall s/frame |",
          "|---|---|---|---|---|---|---|---|"]
    for label, by_v in ab.items():
        for v, runs in by_v.items():
            a = np.array([x["ate"] for x in runs], dtype=float)
            L.append(f"| {label} | {v} | {_f(np.nanmean(a))} | {_f(np.nanmin(a))} | {_f(np.nanmax(a))} | "
                     f"{_m(runs[0]['params']) if runs[0]['params'] else '-'} | "
                     f"{np.mean([x['cpu_fpt'] for x in runs]):.3f} | {np.mean([x['fpt'] for x in runs]):.3f} |")
    ratio_rows = []
    for label, by_v in ab.items():
        if "[D] CP-SA (LRSLAM)" in by_v and "tri-plane (ESLAM)" in by_v:
            f = [np.mean([x["cpu_fpt"] for x in by_v[v]]) for v in ("[D] CP-SA (LRSLAM)", "tri-plane (ESLAM)")]
            ratio_rows.append(f"{label} {f[0] / f[1]:.2f}")
    if ratio_rows:
        L += ["", "CP-SA / tri-plane CPU time per frame, per sequence (means over the seeds above): " +
              ", ".join(ratio_rows) + "."]
    L += ["", ("Parameters: the paper's total (f_g + f_a + decoders) at the run's bound. Paper (ScanNet, Fig. "
          "ablation): SA and "
          "CP take \"4-6 % and 8-12 % less\" parameters than tri-plane. Read as *fewer* that contradicts its own "
          "Table 1 (CP-SA has 87-90 % fewer); read as *of* tri-plane it matches the closed forms at ScanNet "
          "bounds (scene0000: CP-CP 0.71 M = 4.0 %, SA-SA 1.42 M = 8.0 % of 17.63 M) with CP and SA swapped. "
          "On our smaller bounds the ratios are larger (planes grow as L^2, lines as L). The paper also reports "
          "the largest ATE variance for CP-CP [A]; our excerpts are short, so differences between variants "
          "smaller than the seed spread in the table are not significant."), ""]
    # 4. Noise
    nz = res["noise"]
    keys = ("depth_l1_cm", "accuracy_cm", "completion_cm", "completion_ratio", "ate_mean_cm", "ate_rmse_cm")
    L += ["## 4. Depth-noise robustness (Table 4 bottom)", "",
          (f"Synthetic room loop, {size.noise_frames} frames, depth + N(0, 0.05^2) m; mesh metrics with the ESLAM "
          f"protocol (`lrslam eval mesh` default) at {size.eval_points:,} points and {size.depth_views} NICE-SLAM "
          "depth views (paper: Replica room0, 450,000 points, 1000 views); the mesh is evaluated in the GT world "
          "(`initial_pose: gt`, `evaluate_run_mesh`)."), "",
          "| method | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    for r in ("eslam", "lrslam"):
        name = "ESLAM (tri-plane)" if r == "eslam" else "LRSLAM (CP-SA)"
        L.append(f"| {name} | " + " | ".join(_f(nz[r].get(k)) for k in keys) + " |")
        L.append(f"| *paper* {name} | " + " | ".join(_f(paper_t4[r][k]) for k in keys) + " |")
    def wins(k):
        a, b = nz["lrslam"].get(k), nz["eslam"].get(k)
        return a is not None and b is not None and (a > b if k == "completion_ratio" else a < b)

    better = [k for k in keys if wins(k)]
    fb = [f"{'CP-SA' if r == 'lrslam' else 'tri-plane'} {nz[r].get('depth_views_fallback')}" for r in nz
          if nz[r].get("depth_views_fallback") is not None]
    icp = [f"{'CP-SA' if r == 'lrslam' else 'tri-plane'} {nz[r]['icp_translation_cm']:.1f} cm / "
           f"{nz[r]['icp_rotation_deg']:.2f} deg" for r in nz if nz[r].get("icp_translation_cm") is not None]
    L += ["", (f"CP-SA beats tri-plane here on: {', '.join(better) or 'none'} (paper: all but completion ratio; "
          "ATE mean / RMSE differ by 2-3 % there, depth L1 by 63 %, accuracy by 48 %, completion by 41 %). "
          f"Absolute values differ from the paper's: another scene (synthetic room, not Replica room0), "
          f"{size.noise_frames} frames of one lap instead of 2000, CPU-sized iterations. With so few frames parts of "
          "the GT room are never observed or only by a couple of views: completion and completion ratio count "
          "them as missing, and the NICE-SLAM depth views that could not avoid unobserved GT after 100 draws "
          f"(fallback views: {', '.join(fb) or '-'} of {size.depth_views}) add their error to depth L1; the paper's "
          "Replica runs see the whole room. ICP correction applied before the metrics: "
          f"{', '.join(icp) or '-'}."), ""]
    # 5. Convergence
    cv = res["convergence"]
    L += ["## 5. Convergence", "", "![convergence](paper_convergence.png)", "",
          ("First-frame mapping of the synthetic room (pose fixed); loss of the last iteration and depth L1 (cm) of a "
          "quarter-resolution render of that frame after k iterations (one fresh, seeded field per k)."), "",
          "| variant | " + " | ".join(f"k={c['iters']}" for c in next(iter(cv.values()))) + " |",
          "|---|" + "---|" * len(next(iter(cv.values())))]
    for v, curve in cv.items():
        L.append(f"| {v} | " + " | ".join(f"{c['loss']:.4f} / {c['depth_l1_cm']:.1f}" for c in curve) + " |")
    reach = {v: _iters_to(c, CONVERGED_CM) for v, c in cv.items()}
    L += ["", f"(loss / depth L1 cm.) Mapping iterations until the depth L1 first falls below {CONVERGED_CM:g} cm: " +
          ", ".join(f"{v} {'>' + str(cv[v][-1]['iters']) if k is None else k}" for v, k in reach.items()) + ".", ""]
    # The paper: "CP decomposition converges faster than SA decomposition" (geometry). Compare variants that
    # differ only in the geometry encoding: [A] CP-CP vs [C] SA-CP, and [D] CP-SA vs [B] SA-SA.
    pairs = [("[A] CP-CP", "[C] SA-CP"), ("[D] CP-SA (LRSLAM)", "[B] SA-SA")]
    verdicts = []
    for cp, sa in pairs:
        kc, ks = reach.get(cp), reach.get(sa)
        if cp not in reach or sa not in reach:
            continue
        inf = float("inf")
        verdicts.append((cp, sa, (inf if kc is None else kc) <= (inf if ks is None else ks)))
    if verdicts:
        ok = all(v[2] for v in verdicts)
        L += ["Paper: CP geometry converges faster than SA geometry. Pairs that differ only in the geometry "
              "encoding: " + "; ".join(f"{cp} vs {sa}: {'CP first or tied' if w else 'SA first'}"
                                       for cp, sa, w in verdicts) + ". " +
              ("Agrees." if ok else
               "**Disagrees** here. Our reading: every factor starts as N(0, 0.01^2) (ESLAM's feature init; the "
               "paper does not give one), so a CP feature, a product of three factors, starts near 1e-6 and the "
               "gradient of each factor is scaled by the other two (~1e-4); a Six-axis feature is a product of two "
               "and a tri-plane feature is the plane itself, so they leave zero sooner. Only the first frame is "
               "measured (the paper's claim is about whole runs)."), ""]
    L += ["## Timings", "", ", ".join(f"{k} {v:.0f} s" for k, v in timings.items()), ""]
    path.write_text("\n".join(L))
    return path
