"""Speed and memory of the scene representations (paper Table 1 / Fig. ablation variants) on the Replica room0 bound.

For each representation x device x (rays, samples per ray) it times, as median over repetitions:
- ``map``: one mapping step: render random rays with depth-guided samples, ESLAM mapping loss, backward into
  the feature lines/planes and decoders, Adam step;
- ``track``: one tracking step: frozen field, gradient to a camera pose only, Adam step on the pose;
and reports parameter counts (encodings, as the paper) and peak memory (CUDA: ``max_memory_allocated``; CPU:
peak RSS growth of a fresh worker process during the steps). Each row runs in its own process.

Usage: ``python benchmarks/field_speed.py [--sizes 2000x40 500x32] [--reps 5] [--threads N] [--quick]``.
Rows marked "torch kernels" use the pure-PyTorch samplers instead of the default fused numba kernels on CPU.

``--paired`` instead alternates CP-SA and tri-plane steps in one process and reports the median per-pair ratio:
on a shared virtual CPU whose speed drifts by ~1.5x between phases this comparison is the robust one.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from contextlib import ExitStack

ROOM0 = [[-1.9, 7.9], [-2.2, 4.5], [-2.5, 2.3]]
# (label, model preset, overrides applied to both encodings' configs; sa_evaluation only affects Six-axis)
VARIANTS = [
    ("cp-sa (LRSLAM)", "cp-sa", {}),
    ("cp-sa, torch kernels", "cp-sa", {"sampler": "gather"}),
    ("cp-sa, SA direct", "cp-sa", {"sa_evaluation": "direct"}),
    ("cp-cp", "cp-cp", {}),
    ("sa-sa", "sa-sa", {}),
    ("sa-cp", "sa-cp", {}),
    ("triplane (ESLAM)", "triplane", {}),
    ("triplane, torch kernels", "triplane", {"sampler": "gather"}),
    ("triplane, grid_sample", "triplane", {"sampler": "grid_sample"}),
]
QUICK = ("cp-sa (LRSLAM)", "cp-sa, torch kernels", "cp-sa, SA direct", "triplane (ESLAM)", "triplane, torch kernels")


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def _setup(spec: dict):
    """Model, optimisers and the two timed steps for one configuration -> (model, map_step, track_step)."""
    import numpy as np
    import torch

    from lrslam.field.losses import MAPPING_WEIGHTS, TRACKING_WEIGHTS, rendering_loss
    from lrslam.field.model import SceneModel, SceneModelConfig
    from lrslam.field.poses import PoseParams
    from lrslam.field.render import RenderConfig, render_rays

    if spec["threads"]:
        torch.set_num_threads(spec["threads"])
    dev = torch.device(spec["device"])
    cfg = SceneModelConfig.preset(spec["preset"])
    updates = {}
    for role in ("geometry", "appearance"):  # overrides apply to every encoding (sa_evaluation: Six-axis only)
        if spec["overrides"]:
            updates[role] = getattr(cfg, role).model_copy(update=spec["overrides"])
    cfg = cfg.model_copy(update=updates)
    torch.manual_seed(0)
    model = SceneModel(np.array(ROOM0), cfg, dev)
    n_rays, n_samples = spec["rays"], spec["samples"]
    render = RenderConfig(n_stratified=n_samples - 8, n_importance=8)
    gen = torch.Generator().manual_seed(0)
    # random rays from cameras inside the room towards surfaces 1-4 m away (all inside the bound)
    rng = np.random.default_rng(0)
    o = torch.tensor(rng.uniform([0.5, -0.5, -0.5], [5.5, 2.5, 0.5], (n_rays, 3)), dtype=torch.float32, device=dev)
    d = torch.tensor(rng.normal(size=(n_rays, 3)), dtype=torch.float32, device=dev)
    d = d / d.norm(dim=1, keepdim=True)
    depth = torch.tensor(rng.uniform(1.0, 2.0, n_rays), dtype=torch.float32, device=dev)
    rgb = torch.rand(n_rays, 3, device=dev)
    mask = torch.ones(n_rays, dtype=torch.bool, device=dev)
    opt = torch.optim.Adam([{"params": model.encoding_parameters(), "lr": 0.005},
                            {"params": model.decoder_parameters(), "lr": 0.001}])
    pose = PoseParams(np.eye(4), "quat", dev)
    popt = torch.optim.Adam(pose.parameters(), lr=0.001)

    def map_step():
        r = render_rays(model, o, d, depth, model.truncation, render, gen)
        loss, _ = rendering_loss(r, depth, rgb, model.truncation, MAPPING_WEIGHTS, mask, mask)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    def track_step():
        T = pose.matrices()[0]
        r = render_rays(model, o @ T[:3, :3].T + T[:3, 3], d @ T[:3, :3].T, depth, model.truncation, render, gen)
        loss, _ = rendering_loss(r, depth, rgb, model.truncation, TRACKING_WEIGHTS, mask, mask)
        popt.zero_grad(set_to_none=True)
        loss.backward()
        popt.step()

    return model, map_step, track_step


def paired(spec: dict, presets: tuple[str, str] = ("cp-sa", "triplane")) -> dict:
    """Both representations in one process, steps alternated A, B, A, B, ...: each pair sees the same machine
    state, so the ratio is robust to the slow/fast phases of a shared (virtual) CPU. Medians in ms and the
    median of the per-pair ratios A / B."""
    import numpy as np

    out = {}
    setups = [_setup({**spec, "preset": p, "overrides": spec.get("overrides", {})}) for p in presets]
    for kind in ("map", "track"):
        steps = [s[1] if kind == "map" else s[2] for s in setups]
        times = np.zeros((spec["reps"], 2))
        with ExitStack() as stack:
            if kind == "track":  # tracking: frozen fields (cached Six-axis planes), as in worker()
                for m, _, _ in setups:
                    stack.enter_context(m.frozen())
            for st in steps:
                st()  # warm-up
            for i in range(spec["reps"]):
                for j, st in enumerate(steps):
                    t0 = time.perf_counter()
                    st()
                    times[i, j] = 1000 * (time.perf_counter() - t0)
        out[kind] = {"a_ms": float(np.median(times[:, 0])), "b_ms": float(np.median(times[:, 1])),
                     "ratio": float(np.median(times[:, 0] / times[:, 1])),
                     "a_range": [float(times[:, 0].min()), float(times[:, 0].max())]}
    return out


def worker(spec: dict) -> dict:
    """Time one configuration in this process (called in a fresh subprocess)."""
    import numpy as np
    import torch

    from lrslam.threads import flush_denormals

    flush_denormals()   # as a run does (lrslam.threads), before the pools start
    model, map_step, track_step = _setup(spec)
    dev = torch.device(spec["device"])

    def timed(step, reps):
        step()  # warm-up (kernel selection, allocator)
        if dev.type == "cuda":
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        base = _rss_mb()
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            step()
            if dev.type == "cuda":
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t0)
        if dev.type == "cuda":
            mem = torch.cuda.max_memory_allocated() / 2**20
        else:
            mem = max(0.0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - base)
        return 1000 * float(np.median(times)), mem

    reps = spec["reps"] if spec["overrides"].get("sa_evaluation") != "direct" else max(1, min(2, spec["reps"]))
    map_ms, map_mem = timed(map_step, reps)
    with model.frozen():
        track_ms, track_mem = timed(track_step, reps)
    counts = model.parameter_count()
    return {"map_ms": map_ms, "track_ms": track_ms, "map_mem_mb": map_mem, "track_mem_mb": track_mem,
            "geometry": counts["geometry"], "appearance": counts["appearance"], "total": counts["total"],
            "threads": torch.get_num_threads()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["2000x40"], help="rays x samples per ray")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = torch default)")
    ap.add_argument("--devices", nargs="+", default=None, help="default: cpu, plus cuda when available")
    ap.add_argument("--quick", action="store_true", help="only cp-sa and triplane (numba and torch kernels) and "
                    "cp-sa with point-by-point Six-axis")
    ap.add_argument("--torch-kernels", action="store_true",
                    help="with --paired: both models on the torch samplers instead of the numba kernels")
    ap.add_argument("--json", default=None, help="also write the rows to this JSON file")
    ap.add_argument("--paired", action="store_true",
                    help="cp-sa vs triplane alternated step by step in one process (robust ratio on a noisy CPU)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return

    import torch

    devices = args.devices or (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    if args.paired:
        reps = max(args.reps, 10)
        kernels = "torch kernels" if args.torch_kernels else "default kernels (numba on CPU)"
        print(f"paired: cp-sa (A) vs triplane (B), {kernels}, steps alternated in one process, "
              f"median over {reps} pairs")
        for device in devices:
            for size in args.sizes:
                n_rays, n_samples = (int(v) for v in size.lower().split("x"))
                spec = {"device": device, "rays": n_rays, "samples": n_samples, "reps": reps, "threads": args.threads,
                        "overrides": {"sampler": "gather"} if args.torch_kernels else {}}
                r = paired(spec)
                for kind in ("map", "track"):
                    k = r[kind]
                    print(f"{device:5s} {size:>9s} {kind:5s}  cp-sa {k['a_ms']:7.1f} ms "
                          f"(range {k['a_range'][0]:.0f}-{k['a_range'][1]:.0f})  triplane {k['b_ms']:7.1f} ms  "
                          f"cp-sa/triplane {k['ratio']:.2f}", flush=True)
        return
    variants = [v for v in VARIANTS if not args.quick or v[0] in QUICK]
    rows = []
    header = (f"{'representation':24s} {'device':6s} {'rays x samp':>11s} {'map ms':>9s} {'track ms':>9s} "
              f"{'f_g':>9s} {'f_a':>9s} {'total':>9s} {'map MB':>8s} {'track MB':>8s}")
    print(header)
    print("-" * len(header))
    for device in devices:
        for size in args.sizes:
            n_rays, n_samples = (int(v) for v in size.lower().split("x"))
            for label, preset, overrides in variants:
                spec = {"preset": preset, "overrides": overrides, "device": device, "rays": n_rays,
                        "samples": n_samples, "reps": args.reps, "threads": args.threads}
                proc = subprocess.run([sys.executable, __file__, "--worker", json.dumps(spec)], capture_output=True,
                                      text=True)
                if proc.returncode != 0:
                    print(f"{label:24s} {device:6s} {size:>11s}  failed: {proc.stderr.strip().splitlines()[-1]}")
                    continue
                r = json.loads(proc.stdout.strip().splitlines()[-1])
                rows.append({"representation": label, "device": device, "size": size, **r})
                print(f"{label:24s} {device:6s} {size:>11s} {r['map_ms']:9.1f} {r['track_ms']:9.1f} "
                      f"{r['geometry'] / 1e6:8.3f}M {r['appearance'] / 1e6:8.3f}M {r['total'] / 1e6:8.3f}M "
                      f"{r['map_mem_mb']:8.0f} {r['track_mem_mb']:8.0f}", flush=True)
    if rows:
        print(f"(torch threads: {rows[0]['threads']}; median of {args.reps} steps; Replica room0 bound)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
