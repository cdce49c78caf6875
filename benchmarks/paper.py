"""The paper, reproduced side by side: writes ``docs/RESULTS.md`` (and the plots it links) from runs on this machine.

Sections (each number is measured by this script, next to the paper's):
  1. Table 1: f_g / f_a / total parameters per dataset (exact, from the presets' ESLAM bounds) and the CP-SA /
     tri-plane whole-run frame-time ratio, the two alternated in one process.
  2. Memory growth: parameters vs scene side L for tri-plane, CP, SA and CP-SA (log-log plot, fitted slopes).
  3. Ablation [A]-[D] + tri-plane: ATE RMSE over seeds (box plots) on a synthetic scene and the real excerpts in
     ``../shared/data`` (field mode, the paper's setting), with parameters and frame time per variant.
  4. Depth-noise robustness (Table 4 bottom): N(0, 0.05^2) depth noise on a synthetic scene with a GT mesh,
     CP-SA vs tri-plane: depth L1, accuracy, completion, completion ratio (ESLAM mesh protocol), ATE mean / RMSE.
  5. Convergence: first-frame mapping loss and rendered depth L1 vs mapping iteration per variant.

Settings are CPU-sized (stated in the document). Default (full): 5 seeds per variant, ~20 CPU-minutes
(estimated); ``--quick``: 3 seeds, 8 CPU-minutes measured (under 15 minutes on a 2-core CPU not shared with other
sessions); ``--smoke``: a tiny run that exercises every section (< 2 minutes alone, for testing the script). None
is the paper's GPU-sized setting.

Usage::

    python benchmarks/paper.py [--quick | --smoke] [--docs docs] [--work runs/paper] [--threads N] [--reuse]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

VARIANTS = {"[A] CP-CP": "cp-cp", "[B] SA-SA": "sa-sa", "[C] SA-CP": "sa-cp", "[D] CP-SA (LRSLAM)": "lrslam",
            "tri-plane (ESLAM)": "eslam"}
# Paper Table 1 (M parameters f_g, f_a, total; FPT seconds) and Table 4 (Replica room0 with N(0, 0.05^2) noise).
PAPER_T1 = {"replica": {"lrslam": (0.03, 0.83, 0.86, 0.22), "eslam": (1.40, 5.38, 6.79, 0.23)},
            "scannet": {"lrslam": (0.05, 1.33, 1.38, 0.37), "eslam": (3.66, 13.98, 17.63, 0.51)},
            "tum": {"lrslam": (0.03, 0.81, 0.84, 1.22), "eslam": (1.40, 5.36, 6.77, 4.56)}}
# The scene whose ESLAM bound gives each dataset's Table 1 counts (its named scene preset).
PAPER_T1_SCENES = {"replica": "replica-room0", "scannet": "scannet-scene0000", "tum": "tum-fr1-desk"}
PAPER_T4 = {"eslam": {"depth_l1_cm": 3.22, "accuracy_cm": 2.04, "completion_cm": 1.99, "completion_ratio": 98.35,
                      "ate_mean_cm": 3.00, "ate_rmse_cm": 2.64},
            "lrslam": {"depth_l1_cm": 1.20, "accuracy_cm": 1.06, "completion_cm": 1.18, "completion_ratio": 98.28,
                       "ate_mean_cm": 2.94, "ate_rmse_cm": 2.57}}


@dataclass(frozen=True)
class Size:
    """How big each section's runs are."""

    name: str
    frames: int            # synthetic sequence length
    real_frames: int       # frames of each real excerpt
    seeds: int             # ablation seeds per variant
    timing_pairs: int      # alternated CP-SA / tri-plane runs for the FPT ratio
    noise_frames: int
    depth_views: int       # NICE-SLAM depth-L1 views (paper: 1000)
    eval_points: int       # points per mesh (ESLAM: 450,000)
    checkpoints: tuple[int, ...]
    ablation_variants: tuple[str, ...] = tuple(VARIANTS)
    overrides: tuple[str, ...] = field(default_factory=tuple)


SIZES = {
    "smoke": Size("smoke", 4, 3, 1, 1, 4, 3, 5_000, (2, 4), ("[D] CP-SA (LRSLAM)", "tri-plane (ESLAM)"), (
        "field.tracking.iters=3", "field.tracking.n_rays=100", "field.mapping.iters=3", "field.mapping.n_rays=200",
        "field.mapping.first_iters=10", "field.render.n_stratified=8", "field.render.n_importance=4",
        "field.mesh.resolution=0.1")),
    # quick: 8.1 CPU-minutes measured (1 thread: ~9 minutes alone); 60 minutes of wall time when the 2 cores were
    # shared with up to ~30 runnable processes of other sessions.
    "quick": Size("quick", 10, 6, 3, 2, 16, 10, 50_000, (5, 10, 20, 40, 80), tuple(VARIANTS), (
        "field.tracking.iters=8", "field.tracking.n_rays=300", "field.mapping.iters=8", "field.mapping.n_rays=600",
        "field.mapping.first_iters=60", "field.mesh.resolution=0.05")),
    # full: 5 seeds, more frames than quick at quick's iterations: ~20 CPU-minutes (estimated from quick), about an
    # hour on 2 cores shared with other sessions (the preset defaults, 20-30 x 400-800 tracking, take ~5x longer).
    "full": Size("full", 16, 8, 5, 2, 20, 20, 200_000, (5, 10, 20, 40, 80, 160), tuple(VARIANTS), (
        "field.tracking.iters=8", "field.tracking.n_rays=300", "field.mapping.iters=8", "field.mapping.n_rays=600",
        "field.mapping.first_iters=60", "field.mesh.resolution=0.05")),
}


def _shared_data() -> Path:
    return Path(os.environ.get("LRSLAM_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


REUSE = {"on": False}   # --reuse: take a run's metrics from an earlier, identical run in --work


def _run(seq: Path, preset: str, repr_name: str, out: Path, overrides: list[str]) -> dict:
    from lrslam.pipeline.config import build_config
    from lrslam.pipeline.run import run_sequence

    key = {"seq": str(Path(seq).resolve()), "preset": preset, "repr": repr_name, "overrides": list(overrides)}
    done = out / "paper_run.json"
    if REUSE["on"] and done.exists():
        prev = json.loads(done.read_text())
        if prev.get("key") == key:
            return prev["metrics"]
    # the paper's figures are of the online trajectory: no final smoothing (lrslam.backend.smoother) here
    cfg = build_config(preset, repr_name, overrides=[*overrides, "smoothing.enabled=false"], mode="field")
    t = time.process_time()
    m = dict(run_sequence(seq, cfg, out, progress=False).metrics)
    # CPU seconds per frame of this process (1 thread: what the run takes alone); the wall-clock fpt_s also
    # counts the time other processes on a shared machine took from it.
    m["cpu_fpt_s"] = (time.process_time() - t) / max(int(m.get("n_frames", 1)), 1)
    done.write_text(json.dumps({"key": key, "metrics": m}, default=str))
    return m


def _synthetic(work: Path, n: int, noise_sigma: float = 0.0) -> Path:
    from lrslam.datasets.synth.noise import NoiseConfig
    from lrslam.datasets.synth.writer import generate

    tag = f"room_loop_{n}" + (f"_sigma{noise_sigma:g}" if noise_sigma else "")
    return generate(work / "data" / tag, scene="room", trajectory="loop", n_frames=n, seed=0,
                    noise=NoiseConfig(depth_sigma=noise_sigma, seed=0), show_progress=False)


# --------------------------------------------------------------------------------------------- 1. Table 1
def table1(size: Size, work: Path) -> dict:
    from lrslam.field.model import SceneModel
    from lrslam.pipeline.config import build_config

    counts = {}
    for ds in PAPER_T1:
        for r in ("lrslam", "eslam"):
            cfg = build_config(PAPER_T1_SCENES[ds], r)
            c = SceneModel(np.asarray(cfg.bound), cfg.field.model).parameter_count()
            counts[(ds, r)] = (c["geometry"], c["appearance"], c["total"])   # total includes the decoders
    # Whole-run frame time, CP-SA and tri-plane alternated in this process (same sequence, same settings).
    seq = _synthetic(work, size.frames)
    ov = list(size.overrides) + ["output.mesh=false", "output.plots=false"]
    fpt = {"lrslam": [], "eslam": []}
    cpu = {"lrslam": [], "eslam": []}
    _run(seq, "synthetic", "lrslam", work / "timing" / "warmup", ov)   # numba compilation, not timed
    for i in range(size.timing_pairs):
        for r in (("lrslam", "eslam") if i % 2 == 0 else ("eslam", "lrslam")):
            m = _run(seq, "synthetic", r, work / "timing" / f"{r}_{i}", ov)
            fpt[r].append(m["fpt_s"])
            cpu[r].append(m["cpu_fpt_s"])
    ratios = [a / b for a, b in zip(fpt["lrslam"], fpt["eslam"])]
    cpu_ratios = [a / b for a, b in zip(cpu["lrslam"], cpu["eslam"])]
    return {"counts": counts, "fpt": fpt, "ratios": ratios, "cpu_fpt": cpu, "cpu_ratios": cpu_ratios}


# --------------------------------------------------------------------------------------- 2. memory growth
def memory_growth(docs: Path) -> dict:
    from lrslam.field.model import SceneModel, SceneModelConfig

    sides = [1.2, 2.4, 4.8, 9.6, 19.2]
    kinds = {"tri-plane": "eslam", "CP (CP-CP)": "cp-cp", "SA (SA-SA)": "sa-sa", "CP-SA": "lrslam"}
    rows = {k: [SceneModel(np.array([[0.0, L]] * 3), SceneModelConfig.preset(p)).parameter_count()["encodings"]
                for L in sides] for k, p in kinds.items()}
    slopes = {k: float(np.polyfit(np.log(sides[2:]), np.log(v[2:]), 1)[0]) for k, v in rows.items()}
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    for k, v in rows.items():
        ax.loglog(sides, v, "o-", label=f"{k} (slope {slopes[k]:.2f})")
    ax.set_xlabel("scene side L (m), cubic scene")
    ax.set_ylabel("encoding parameters f_g + f_a")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(docs / "paper_memory.png", dpi=120)
    plt.close(fig)
    return {"sides": sides, "rows": rows, "slopes": slopes}


# --------------------------------------------------------------------------------------------- 3. ablation
def ablation(size: Size, work: Path, docs: Path) -> dict:
    root = _shared_data()
    seqs = [("synthetic room loop", _synthetic(work, size.frames), "synthetic", [])]
    for label, pattern, preset in (("TUM fr1/rpy excerpt", "tum*rpy*", "tum-cpu"),
                                   ("7-Scenes redkitchen excerpt", "7scenes*kitchen*", "7scenes-cpu")):
        found = sorted(root.glob(pattern))
        if found:
            seqs.append((label, found[0], preset, [f"dataset.options.max_frames={size.real_frames}"]))
    res: dict = {}
    for label, path, preset, extra in seqs:
        res[label] = {}
        for vname in size.ablation_variants:
            r, runs = VARIANTS[vname], []
            for s in range(size.seeds):
                ov = list(size.overrides) + extra + [f"field.seed={s}", "output.mesh=false", "output.plots=false"]
                m = _run(path, preset, r, work / "ablation" / preset / r / f"seed{s}", ov)
                runs.append({"ate": m.get("ate_rmse_cm", float("nan")), "fpt": m["fpt_s"], "cpu_fpt": m["cpu_fpt_s"],
                             "params": m.get("parameters", {}).get("total")})
            res[label][vname] = runs
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(res), figsize=(4.5 * len(res), 4), squeeze=False)
    for ax, (label, by_v) in zip(axes[0], res.items()):
        ax.boxplot([[x["ate"] for x in runs] for runs in by_v.values()], showmeans=True)
        ax.set_xticks(range(1, len(by_v) + 1), [v.split(" ")[0] if v.startswith("[") else "tri" for v in by_v])
        ax.set_title(label, fontsize=9)
        ax.set_ylabel("ATE RMSE (cm)")
    fig.tight_layout()
    fig.savefig(docs / "paper_ablation.png", dpi=120)
    plt.close(fig)
    return res


# ---------------------------------------------------------------------------------------- 4. depth noise
def noise_robustness(size: Size, work: Path) -> dict:
    from lrslam.errors import InputError
    from lrslam.datasets import open_sequence
    from lrslam.evaluation.mesh_eval import evaluate_run_mesh
    from lrslam.evaluation.mesh_protocol import get_protocol

    seq_path = _synthetic(work, size.noise_frames, noise_sigma=0.05)
    seq = open_sequence(seq_path)
    proto = get_protocol("eslam", n_points=size.eval_points, depth_views=size.depth_views)
    out = {}
    for r in ("lrslam", "eslam"):
        run_dir = work / "noise" / r
        m = _run(seq_path, "synthetic", r, run_dir, list(size.overrides) + ["output.plots=false",
                                                                          "output.eval_mesh_points=1000"])
        import trimesh

        mesh = trimesh.load(run_dir / "mesh.ply", force="mesh", process=False)
        try:
            rec = evaluate_run_mesh(mesh, seq.gt_mesh_path, seq.gt_poses(), seq.K, seq.width, seq.height, None,
                                    world_is_gt=True, protocol=proto)
        except InputError as e:  # an empty mesh (tiny --smoke settings) has no metrics: say so, do not stop
            print(f"[paper] noise, {r}: no mesh metrics ({e})", flush=True)
            rec = {"mesh_error": str(e)}
        out[r] = {**{k: rec.get(k) for k in ("depth_l1_cm", "accuracy_cm", "completion_cm", "completion_ratio",
                                             "depth_views_fallback", "icp_translation_cm", "icp_rotation_deg")},
                  "ate_mean_cm": m.get("ate_mean_cm"), "ate_rmse_cm": m.get("ate_rmse_cm")}
    return out


# ----------------------------------------------------------------------------------------- 5. convergence
def convergence(size: Size, work: Path, docs: Path) -> dict:
    from lrslam.field.render import render_image
    from lrslam.field.slam import FieldSLAM
    from lrslam.datasets import open_sequence
    from lrslam.pipeline.config import build_config

    seq = open_sequence(_synthetic(work, size.frames))
    f0 = seq[0]
    s = 4   # depth L1 on a quarter-resolution render of frame 0
    Ks = f0.K.copy()
    Ks[:2] /= s
    w, h = f0.width // s, f0.height // s
    import cv2

    gt_small = cv2.resize(f0.depth, (w, h), interpolation=cv2.INTER_NEAREST)
    res = {}
    for vname, r in VARIANTS.items():
        curve = []
        for k in size.checkpoints:
            cfg = build_config("synthetic", r, overrides=list(size.overrides) + [f"field.mapping.first_iters={k}"])
            fcfg = cfg.field
            slam = FieldSLAM(fcfg, np.asarray(seq.bound), f0.K, f0.height, f0.width)
            stats = slam.initialise(0, f0.rgb, f0.depth, f0.T_w_c_gt)
            with slam.model.frozen():
                d, _ = render_image(slam.model, Ks, f0.T_w_c_gt, h, w, slam.model.truncation, fcfg.render)
            ok = gt_small > 0
            l1_cm = 100.0 * float(np.abs(d - gt_small)[ok].mean())
            curve.append({"iters": k, "loss": stats["loss"], "depth_l1_cm": l1_cm})
        res[vname] = curve
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    for vname, curve in res.items():
        it = [c["iters"] for c in curve]
        axes[0].plot(it, [c["loss"] for c in curve], "o-", label=vname)
        axes[1].plot(it, [c["depth_l1_cm"] for c in curve], "o-", label=vname)
    axes[0].set_ylabel("mapping loss (last iteration)")
    axes[1].set_ylabel("depth L1 of frame 0 (cm)")
    for ax in axes:
        ax.set_xlabel("first-frame mapping iterations")
        ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(docs / "paper_convergence.png", dpi=120)
    plt.close(fig)
    return res


def main() -> int:
    from paper_report import write_report   # sibling module (benchmarks/ is put on sys.path below)

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--quick", action="store_true", help="CPU-sized, < 15 minutes on 2 cores")
    g.add_argument("--smoke", action="store_true", help="tiny, < 2 minutes: exercises every section")
    ap.add_argument("--docs", type=Path, default=Path(__file__).resolve().parents[1] / "docs")
    ap.add_argument("--work", type=Path, default=Path("runs/paper"))
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    ap.add_argument("--reuse", action="store_true", help="resume: reuse the runs an interrupted call with the same "
                    "--work finished (same sequence, preset, representation and overrides)")
    a = ap.parse_args()
    REUSE["on"] = a.reuse
    size = SIZES["smoke" if a.smoke else "quick" if a.quick else "full"]
    if a.threads:
        import torch

        torch.set_num_threads(a.threads)
    from lrslam.threads import flush_denormals

    flush_denormals()   # as `lrslam run` (lrslam.threads), before any pool starts
    a.docs.mkdir(parents=True, exist_ok=True)
    work = a.work / size.name
    t0 = time.perf_counter()
    timings = {}
    results = {}
    load_start = os.getloadavg()[0]
    for name, fn in (("table1", lambda: table1(size, work)), ("memory", lambda: memory_growth(a.docs)),
                     ("ablation", lambda: ablation(size, work, a.docs)),
                     ("noise", lambda: noise_robustness(size, work)),
                     ("convergence", lambda: convergence(size, work, a.docs))):
        t = time.perf_counter()
        results[name] = fn()
        timings[name] = time.perf_counter() - t
        print(f"[paper] {name}: {timings[name]:.1f} s", flush=True)
    timings["total"] = time.perf_counter() - t0
    import torch

    results["load"] = {"cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(), "start": load_start,
                       "end": os.getloadavg()[0]}
    path = write_report(a.docs / "RESULTS.md", size, results, timings, PAPER_T1, PAPER_T4)
    saved = {k: v for k, v in results.items() if k != "table1"} | {"timings": timings}
    (work / "results.json").write_text(json.dumps(saved, indent=1,
                                                  default=str))
    print(f"[paper] wrote {path} in {timings['total']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from lrslam.logs import setup_console_logging

    setup_console_logging()
    sys.exit(main())
