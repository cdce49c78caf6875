"""Field-only vs frontend-only vs graph-fused SLAM, side by side, over several seeds: the product promise
"fused is never worse than the best of its parts" checked on every sequence.

Sequences (``--suite``):

- ``synthetic``: a generated loop (150 frames by default) with Kinect-like depth noise plus a constant
  Gaussian term (sigma = 1 cm), and a fast camera: an orbit at about 5.5 cm and 2.5 deg per frame
  (``--orbit-frames``, default 72; same noise; ``lrslam synth --trajectory orbit --step-cm 6 --step-deg 2.4``);
- ``real``: the real excerpts in ``../shared/data``, when present: TUM fr1/rpy (120 frames, every frame) and
  7-Scenes redkitchen (every 4th of 500 frames, ~3 cm / 6 deg apart); ``--stride 3`` multiplies those strides
  (three times the motion per frame); and TUM fr1/xyz in full (798 frames) when ``--tum-full DIR`` (or the
  ``LRSLAM_TUM_FULL`` environment variable) names a folder holding ``rgbd_dataset_freiburg1_xyz`` (kept outside
  the repo; skipped with one line when absent; not strided).

``frontend+graph`` is the frontend with its own pose graph (its keyframe registrations and verified loops, no
field: ``--mode frontend --set parts.backend=graph --set backend.factors=[odometry,loop]``), the classical
loop-closing pipeline a user could run instead of the hybrid. ``frontend`` (the CPU presets' frontend mode)
refines slow frames against a TSDF model of the frames tracked so far (``odometry.model``); fused runs the
frontend without it, frame to frame: ``frontend-f2f`` (``--mode frontend --set odometry.model.enabled=false``).
The promise is checked against the stronger of the two, ``frontend``; ``frontend+graph`` and ``frontend-f2f``
each get their own comparison line (PASS / FAIL, never hidden), outside the promise.

Per sequence every variant runs once per seed (``--seeds``, default 3): the field's ray sampling is random, and
Open3D's multi-threaded registration does not repeat bit for bit, so the frontend alone drifts differently from
run to run as well (frame to frame on fr1/xyz: 3.91 and 4.12 cm in two threaded runs, 4.55 on one thread; only ``--set
deterministic=true`` runs repeat exactly). The table gives ATE RMSE mean, spread (min-max) and every seed,
s/frame with the first-third and last-third means (does the rate collapse as loops accumulate?), keyframes,
loops, graph solves and re-maps. The check line per sequence is ``fused <= min(field, frontend)`` on the means;
it prints FAIL when it fails (never hidden), with the margin and the standard error of fused's mean over its
seeds, so a reader sees whether a verdict is within the runs' noise (the verdict itself stays on the means).

``--ablation N`` adds fused rows with one factor set each (``backend.factors``) over N seeds, to show which
factors earn their place.

Usage::

    python benchmarks/modes.py [--suite synthetic|real|all] [--only tum|7scenes] [--stride N] [--seeds 3]
                               [--frames 150] [--max-frames N] [--ablation SEEDS] [--set key=value ...]
                               [--threads N] [--out runs/bench_modes]

Every run writes its own run folder under ``--out``; the tables are printed and saved as
``--out/<suite>/modes.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

# Runs beside the three modes, each printed with its own comparison line, not counted in the promise: the frontend
# with its own pose graph (keyframe registrations and loops, no field; not one of fused's parts), and the frontend
# without its frame-to-model refinement (odometry.model): fused's own frontend, weaker than `frontend` mode's.
OTHERS = {"frontend+graph": (["parts.backend=graph", 'backend.factors=["odometry", "loop"]'],
                             "the classical pipeline, not one of fused's parts"),
          "frontend-f2f": (["odometry.model.enabled=false"], "fused's own frontend, frame to frame; the promise "
                           "checks the stronger frontend mode")}
MODES = ("field", "frontend", "frontend+graph", "frontend-f2f", "fused")

ABLATION = {"fused[odometry,loop]": ["odometry", "loop"], "fused[field,loop]": ["field", "loop"],
            "fused[odometry,field]": ["odometry", "field"]}


def _jobs(preset: str, overrides: list[str], seeds: int, ablation: int,
          only: tuple[str, ...] = MODES) -> dict[str, dict]:
    """label -> resolved config dict (labels ``<variant>/s<seed>``); ``only``: the modes to run (of
    :data:`MODES`)."""
    from lrslam.pipeline.config import build_config

    jobs = {}
    variants = {"frontend": ("frontend", [], seeds)} if "frontend" in only else {}
    variants |= {name: ("frontend", extra, seeds) for name, (extra, _) in OTHERS.items() if name in only}
    variants |= {m: (m, [], seeds) for m in ("field", "fused") if m in only}
    variants |= {k: ("fused", [f"backend.factors={json.dumps(v)}"], ablation) for k, v in ABLATION.items()}
    for name, (mode, extra, n) in variants.items():
        for s in range(n):
            cfg = build_config(preset, overrides=overrides + extra + [f"field.seed={s}"], mode=mode)
            jobs[f"{name}/s{s}"] = cfg.model_dump(mode="json")
    return jobs


def _summaries(results: dict[str, dict]) -> dict[str, dict]:
    """Group per-seed metrics by variant."""
    out: dict[str, dict] = {}
    for label, m in results.items():
        out.setdefault(label.split("/")[0], {"runs": []})["runs"].append(m)
    for v in out.values():
        ok = [m for m in v["runs"] if "ate_rmse_cm" in m and m["ate_rmse_cm"] is not None]
        ates = np.array([m["ate_rmse_cm"] for m in ok])
        v["ate"] = ates
        v["errors"] = [m["error"] for m in v["runs"] if "error" in m]
        v["mean"] = float(ates.mean()) if len(ates) else float("nan")
        v["sem"] = float(ates.std(ddof=1) / np.sqrt(len(ates))) if len(ates) > 1 else float("nan")
        loops = [m["loops"] for m in ok if m.get("loops")]
        v["loops"] = ({k: float(np.mean([lp[k] for lp in loops])) for k in loops[0]} if loops else None)
        for key in ("fpt_s", "fpt_first_third_s", "fpt_last_third_s", "n_keyframes", "n_loop_closures",
                    "n_graph_solves", "n_remaps", "refinements_rejected", "frontend_ate_rmse_cm",
                    "online_ate_rmse_cm", "unsmoothed_ate_rmse_cm", "seeds_weak", "seeds_overruled_by_field"):
            vals = [m[key] for m in ok if m.get(key) is not None]
            v[key] = float(np.mean(vals)) if vals else None
    return out


def _fmt(x, f="{:.2f}") -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f.format(x)


def _loops(lp: dict | None) -> str:
    """``proposed / unverified, disputed, inconsistent`` (means over seeds) or ``-`` without a loop closer."""
    if not lp:
        return "-"
    return (f"{lp['proposed']:.0f} / {lp['unverified']:.0f}, {lp['disputed']:.0f}, {lp['inconsistent']:.0f}")


def report(title: str, results: dict[str, dict]) -> tuple[str, bool]:
    """Markdown table + the promise check for one sequence."""
    s = _summaries(results)
    lines = [f"## {title}", "",
             "| variant | ATE RMSE cm: mean | spread | per seed | before smoothing | before final refinement | s/frame | "
             "first / last third | keyframes | "
             "loops kept | loops proposed / rejected (registration, map, graph) | solves | re-maps | "
             "refinements rejected | seeds weak / overruled |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, v in s.items():
        a = v["ate"]
        spread = f"{a.min():.2f}-{a.max():.2f}" if len(a) else "-"
        per = ", ".join(f"{x:.2f}" for x in a) + (f" ({len(v['errors'])} failed)" if v["errors"] else "")
        thirds = f"{_fmt(v['fpt_first_third_s'], '{:.3f}')} / {_fmt(v['fpt_last_third_s'], '{:.3f}')}"
        lines.append(f"| {name} | {_fmt(v['mean'])} | {spread} | {per} | {_fmt(v['unsmoothed_ate_rmse_cm'])} | "
                     f"{_fmt(v['online_ate_rmse_cm'])} | "
                     f"{_fmt(v['fpt_s'], '{:.3f}')} | {thirds} | "
                     f"{_fmt(v['n_keyframes'], '{:.0f}')} | {_fmt(v['n_loop_closures'], '{:.0f}')} | "
                     f"{_loops(v['loops'])} | "
                     f"{_fmt(v['n_graph_solves'], '{:.0f}')} | {_fmt(v['n_remaps'], '{:.0f}')} | "
                     f"{_fmt(v['refinements_rejected'], '{:.0f}')} | "
                     f"{_fmt(v['seeds_weak'], '{:.0f}')} / {_fmt(v['seeds_overruled_by_field'], '{:.0f}')} |")
    if not all(k in s for k in ("field", "frontend", "fused")):
        return "\n".join(lines + [""]), True   # an ablation-only table: no promise to check
    best = min(s["field"]["mean"], s["frontend"]["mean"])
    ok = bool(s["fused"]["mean"] <= best)
    f = s["fused"]
    noise = (f"; fused - min = {f['mean'] - best:+.2f} cm, the standard error of fused's mean "
             f"{f['sem']:.2f} over {len(f['ate'])} seeds" if np.isfinite(f["sem"]) else "")
    lines += ["", f"{'PASS' if ok else 'FAIL'}  fused <= min(field, frontend): fused {f['mean']:.2f}, "
                  f"field {s['field']['mean']:.2f}, frontend {s['frontend']['mean']:.2f} cm (means{noise})"]
    for name, (_, what) in OTHERS.items():
        if name in s:
            other = s[name]["mean"]
            lines.append(f"{'PASS' if s['fused']['mean'] <= other else 'FAIL'}  fused <= {name} ({what}; not "
                         f"counted in the promise): fused {s['fused']['mean']:.2f}, {name} {other:.2f} cm")
    return "\n".join(lines + [""]), ok


def _run(seq: Path, preset: str, overrides: list[str], a, out: Path) -> tuple[str, bool]:
    from lrslam.tools.batch import run_batch

    results = run_batch([seq], _jobs(preset, overrides, a.seeds, a.ablation, tuple(a.modes.split(","))), out,
                        progress=not a.quiet)
    text, ok = report(f"{seq.name} ({preset}{', ' + ' '.join(overrides) if overrides else ''})",
                      next(iter(results.values())))
    print("\n" + text, flush=True)
    return text, ok


def main() -> int:
    from lrslam.logs import setup_console_logging

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", choices=("synthetic", "real", "all"), default="all")
    ap.add_argument("--frames", type=int, default=150, help="synthetic loop length")
    ap.add_argument("--orbit-frames", type=int, default=72, help="fast synthetic orbit length (0: none)")
    ap.add_argument("--data-seed", type=int, default=0, help="seed of the synthetic sequence")
    ap.add_argument("--seeds", type=int, default=3, help="field seeds per field / fused variant")
    ap.add_argument("--max-frames", type=int, default=None, help="truncate the real sequences")
    ap.add_argument("--stride", type=int, default=1, help="multiply the real sequences' frame strides")
    ap.add_argument("--tum-full", type=Path, default=os.environ.get("LRSLAM_TUM_FULL"),
                    help="folder holding the full TUM rgbd_dataset_freiburg1_xyz (default: $LRSLAM_TUM_FULL)")
    ap.add_argument("--only", choices=("tum", "7scenes", "xyz"), default=None, help="one real sequence only")
    ap.add_argument("--ablation", type=int, default=0, metavar="SEEDS",
                    help="add one fused row per factor set, over this many seeds (0: none)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="config override key=value")
    ap.add_argument("--threads", type=int, default=None,
                    help="CPU threads (torch, numba, OpenMP; default: the libraries' choice)")
    ap.add_argument("--modes", default=",".join(MODES), help="which of the modes to run (the promise check needs "
                    "field, frontend and fused; frontend+graph and frontend-f2f add their own lines)")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    ap.add_argument("--out", type=Path, default=Path("runs/bench_modes"))
    a = ap.parse_args()
    setup_console_logging()
    from lrslam.threads import flush_denormals, set_threads

    if a.threads:
        set_threads(a.threads)   # torch, numba and (before Open3D loads) OpenMP
    flush_denormals()            # as `lrslam run`: before any pool starts
    texts, oks = [], []
    if a.suite in ("synthetic", "all"):
        from lrslam.datasets.synth.noise import NoiseConfig
        from lrslam.datasets.synth.writer import generate

        noise = NoiseConfig(depth_sigma=0.01, kinect=True, seed=a.data_seed)
        seq = generate(a.out / "data" / f"room_loop_{a.frames}", scene="room", trajectory="loop", n_frames=a.frames,
                       seed=a.data_seed, width=320, height=240, noise=noise, reuse=True)
        t, ok = _run(Path(seq), "synthetic", a.overrides, a, a.out / "synthetic")
        texts.append(t)
        oks.append(ok)
        if a.orbit_frames:
            seq = generate(a.out / "data" / f"room_orbit_{a.orbit_frames}", scene="room", trajectory="orbit",
                           n_frames=a.orbit_frames, seed=a.data_seed, width=320, height=240, noise=noise, reuse=True,
                           trans_step=0.06, rot_step_deg=2.4)
            t, ok = _run(Path(seq), "synthetic", a.overrides, a, a.out / "synthetic-orbit")
            texts.append(t)
            oks.append(ok)
    if a.suite in ("real", "all"):
        root = Path(os.environ.get("LRSLAM_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
        ov = list(a.overrides) + ([f"dataset.options.max_frames={a.max_frames}"] if a.max_frames else [])
        for preset, pattern, stride in (("tum-cpu", "tum*rpy*", 1), ("7scenes-cpu", "7scenes*kitchen*", 4)):
            paths = sorted(root.glob(pattern))
            if a.only and not preset.startswith(a.only):
                continue
            if not paths:
                print(f"\n(no {preset} data under {root}; skipped)")
                continue
            st = stride * a.stride
            t, ok = _run(paths[0], preset, ov + ([f"dataset.options.stride={st}"] if st > 1 else []), a,
                         a.out / f"{preset}-stride{st}")
            texts.append(t)
            oks.append(ok)
    if a.suite in ("real", "all") and a.only in (None, "xyz"):
        xyz = sorted(Path(a.tum_full).glob("*freiburg1_xyz*")) if a.tum_full else []
        if not xyz:
            print(f"\n(no rgbd_dataset_freiburg1_xyz under --tum-full / $LRSLAM_TUM_FULL ({a.tum_full}); skipped)")
        else:
            t, ok = _run(xyz[0], "tum-cpu", ov, a, a.out / "tum-cpu-fr1-xyz")
            texts.append(t)
            oks.append(ok)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "modes.md").write_text("\n".join(texts))
    (a.out / "args.json").write_text(json.dumps({k: str(v) for k, v in vars(a).items()}, indent=2))
    print(f"\n{sum(oks)} of {len(oks)} sequences keep the promise; tables in {a.out / 'modes.md'}")
    return 0 if all(oks) else 1


if __name__ == "__main__":
    sys.exit(main())
