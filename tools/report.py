"""The comparison report of a folder of runs (``lrslam report RUNS_DIR``; also written at the end of a batch).

Writes into RUNS_DIR: ``comparison.md`` and ``comparison.csv`` (per sequence and variant -- mode, or
mode-representation --: runs ok / failed, ATE RMSE and ATE mean as mean ± std over the runs (seeds; sample
standard deviation, n - 1), every seed's value, s/frame, field parameters, mesh metrics where a GT mesh was
evaluated), and ``report.html``: a self-contained page (figures embedded as data URIs, copies in
``report_files/``) with those tables, an ATE box plot over seeds per sequence, the trajectories of all variants
(the median-ATE run of each) overlaid on the ground truth the runs were evaluated against, frame time per stage,
and every failed job with its error.

Runs are found from the batch manifest ``batch.json`` when there is one (it also knows jobs that failed before
writing anything), else from every folder below RUNS_DIR holding a ``run.log``.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import logging
import re
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from lrslam.errors import InputError
from lrslam.pipeline.run_folder import read_run_record

__all__ = ["collect_runs", "summarise", "comparison_markdown", "write_tables", "write_report"]

log = logging.getLogger(__name__)

FILES_DIR = "report_files"
MESH_KEYS = (("mesh_accuracy_cm", "mesh acc cm"), ("mesh_completion_cm", "mesh comp cm"),
             ("mesh_completion_ratio", "mesh comp %"))


# ------------------------------------------------------------------------------------------------ collecting
def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _last_error(run_dir: Path) -> str:
    try:
        lines = (run_dir / "run.log").read_text().splitlines()
    except OSError:
        return "no metrics.json and no run.log"
    failed = [ln.split("job failed: ", 1)[1] for ln in lines if " ERROR lrslam.tools.batch: job failed: " in ln]
    if failed:
        return failed[-1]
    errors = [ln.split(": ", 1)[-1] for ln in lines if " ERROR " in ln]
    return "did not finish" + (f" ({errors[-1]})" if errors else " (no metrics.json)")


def _discover(root: Path) -> list[dict[str, Any]]:
    """Entries for every run folder below ``root`` (a folder with ``run.log``), keys from its config.yaml;
    sequences are named as in a batch (folder name, with parent folders where two share it)."""
    from lrslam.tools.batch_grid import SequenceSpec, name_sequences

    found = []
    for log_file in sorted(root.rglob("run.log")):
        d = log_file.parent
        rec = read_run_record(d) or {}
        found.append((d.relative_to(root).as_posix(), rec, (rec.get("provenance") or {}).get("sequence")))
    paths = list(dict.fromkeys(seq for _, _, seq in found if seq))
    names = {p: s.name for p, s in zip(paths, name_sequences([SequenceSpec(p) for p in paths]), strict=True)}
    entries = []
    for rel, rec, seq in found:
        rep = ((rec.get("provenance") or {}).get("presets") or {}).get("representation")
        mode = rec.get("mode", "?")
        with_field = (rec.get("parts") or {}).get("refiner", "field") != "none"   # no field: no representation
        metrics = _read_json(root / rel / "metrics.json")
        entries.append({
            "name": rel, "sequence": seq, "sequence_name": names.get(seq, rel.split("/")[0]),
            "variant": f"{mode}-{rep}" if rep and with_field else mode, "mode": mode,
            "representation": rep, "seed": (rec.get("field") or {}).get("seed", 0), "run_dir": rel,
            "status": (metrics or {}).get("status", "failed"),
            "error": None if metrics else _last_error(root / rel)})
    return entries


def collect_runs(runs_dir: str | Path) -> list[dict[str, Any]]:
    """Every run of ``runs_dir`` as a dict (name, sequence, sequence_name, variant, mode, representation, seed,
    run_dir, status, error) plus ``metrics`` (its metrics.json, or None). InputError when the folder is missing
    or holds no runs."""
    root = Path(runs_dir)
    if not root.is_dir():
        raise InputError(f"{root}: runs folder not found")
    manifest = _read_json(root / "batch.json")
    entries = list(manifest["jobs"]) if manifest and isinstance(manifest.get("jobs"), list) else _discover(root)
    if not entries:
        raise InputError(f"{root}: no runs found (no batch.json and no run folder with a run.log below it)")
    for e in entries:
        e["metrics"] = _read_json(root / e["run_dir"] / "metrics.json") if e["status"] in ("ok", "degraded") \
            else None
    return entries


# ------------------------------------------------------------------------------------------------ statistics
def _mean_std(values: list[float]) -> tuple[float, float, int] | None:
    """(mean, sample std, n) of the finite values (std 0 for one value), None when there is none."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if not len(v):
        return None
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0, len(v)


def summarise(entries: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, Any]]]:
    """``{sequence_name: {variant: stats}}``; stats: ``runs`` (all entries), ``ok`` (those with metrics),
    ``failed``, ``pending``, ``ate_rmse`` / ``ate_mean`` ((mean, std, n) or None), ``per_seed`` ([(seed, rmse)]),
    ``fpt_s`` (mean s/frame), ``stages`` (stage -> mean s/frame), ``parameters`` (of the first run), and
    ``mesh`` (key -> (mean, std, n) or None)."""
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for e in entries:
        g = out.setdefault(e["sequence_name"], {}).setdefault(e["variant"], {"runs": [], "ok": [], "failed": [],
                                                                              "pending": 0})
        g["runs"].append(e)
        g["mode"], g["representation"] = e["mode"], e.get("representation")
        if e["status"] == "failed":
            g["failed"].append(e)
        elif e.get("metrics"):
            g["ok"].append(e)
        else:
            g["pending"] += 1
    for by_variant in out.values():
        for g in by_variant.values():
            ms = [e["metrics"] for e in g["ok"]]
            g["ate_rmse"] = _mean_std([m.get("ate_rmse_cm") for m in ms])
            g["ate_mean"] = _mean_std([m.get("ate_mean_cm") for m in ms])
            g["per_seed"] = sorted((e["seed"], e["metrics"].get("ate_rmse_cm")) for e in g["ok"])
            fpt = _mean_std([m.get("fpt_s") for m in ms])
            g["fpt_s"] = fpt[0] if fpt else None
            stages: dict[str, list[float]] = {}
            for m in ms:
                for k, v in (m.get("timings") or {}).items():
                    stages.setdefault(k, []).append(v.get("per_frame_s"))
            g["stages"] = {k: _mean_std(v)[0] for k, v in stages.items() if _mean_std(v)}
            g["parameters"] = next((m["parameters"] for m in ms if m.get("parameters")), None)
            g["mesh"] = {k: _mean_std([m.get(k) for m in ms]) for k, _ in MESH_KEYS}
    return out


def _pm(ms: tuple[float, float, int] | None, fmt: str = "{:.2f}") -> str:
    if ms is None:
        return "-"
    return f"{fmt.format(ms[0])} ± {fmt.format(ms[1])}" if ms[2] > 1 else f"{fmt.format(ms[0])} (1 run)"


def _num(x, fmt: str) -> str:
    return "-" if x is None or not np.isfinite(x) else fmt.format(x)


def _params(p: dict[str, Any] | None) -> str:
    if not p or p.get("total") is None:
        return "-"
    return f"{p['total'] / 1e6:.3f} M" + (f" + {p['decoders']:,} dec" if p.get("decoders") else "")


def _runs_cell(g: dict[str, Any]) -> str:
    text = f"{len(g['ok'])}/{len(g['runs'])}"
    if g["failed"]:
        text += f" ({len(g['failed'])} failed)"
    if g["pending"]:
        text += f" ({g['pending']} pending)"
    return text


HEAD = ["sequence", "variant", "runs ok", "ATE RMSE cm (mean ± std)", "ATE mean cm (mean ± std)",
        "ATE RMSE per seed", "s/frame", "field parameters"] + [label for _, label in MESH_KEYS]


def _rows(summary) -> list[list[str]]:
    rows = []
    for seq, by_variant in summary.items():
        for variant, g in by_variant.items():
            per_seed = ", ".join(f"s{s}: {_num(v, '{:.2f}')}" for s, v in g["per_seed"]) or "-"
            rows.append([seq, variant, _runs_cell(g), _pm(g["ate_rmse"]), _pm(g["ate_mean"]), per_seed,
                         _num(g["fpt_s"], "{:.3f}"), _params(g["parameters"])]
                        + [_pm(g["mesh"][k]) for k, _ in MESH_KEYS])
    return rows


def _failed(entries) -> list[dict[str, Any]]:
    return [e for e in entries if e["status"] == "failed"]


def comparison_markdown(entries: list[dict[str, Any]]) -> str:
    """The comparison table (markdown), then the failed jobs with their errors."""
    lines = ["| " + " | ".join(HEAD) + " |", "|" + "---|" * len(HEAD)]
    lines += ["| " + " | ".join(r) + " |" for r in _rows(summarise(entries))]
    failed = _failed(entries)
    if failed:
        lines += ["", "Failed jobs:", ""] + [f"- `{e['name']}`: {e['error']}" for e in failed]
    return "\n".join(lines) + "\n"


def _csv_text(summary) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["sequence", "variant", "mode", "representation", "runs", "runs_ok", "runs_failed",
                "ate_rmse_cm_mean", "ate_rmse_cm_std", "ate_mean_cm_mean", "ate_mean_cm_std",
                "ate_rmse_cm_per_seed", "fpt_s", "parameters_total"] + [f"{k}_mean" for k, _ in MESH_KEYS])
    for seq, by_variant in summary.items():
        for variant, g in by_variant.items():
            ms = [g["ate_rmse"], g["ate_mean"]]
            w.writerow([seq, variant, g["mode"], g["representation"] or "", len(g["runs"]), len(g["ok"]),
                        len(g["failed"])] + [x for m in ms for x in (m[:2] if m else ("", ""))]
                       + [";".join(f"s{s}={v}" for s, v in g["per_seed"]), g["fpt_s"] if g["fpt_s"] is not None
                          else "", (g["parameters"] or {}).get("total", "")]
                       + [g["mesh"][k][0] if g["mesh"][k] else "" for k, _ in MESH_KEYS])
    return buf.getvalue()


def write_tables(runs_dir: str | Path, entries: list[dict[str, Any]] | None = None) -> tuple[Path, Path]:
    """Write ``comparison.md`` and ``comparison.csv`` into ``runs_dir``; returns their paths."""
    root = Path(runs_dir)
    entries = collect_runs(root) if entries is None else entries
    md, cs = root / "comparison.md", root / "comparison.csv"
    md.write_text(comparison_markdown(entries))
    cs.write_text(_csv_text(summarise(entries)))
    return md, cs


# ------------------------------------------------------------------------------------------------ figures
def _ground_truth(root: Path, e: dict[str, Any]):
    """The ground truth the run was evaluated against ((ts, poses) or None), from the run's own config."""
    from lrslam.datasets import open_sequence
    from lrslam.pipeline.config import RECORD_KEYS, RunConfig
    from lrslam.evaluation.ate import ground_truth_samples

    rec = read_run_record(root / e["run_dir"]) or {}
    path = (rec.get("provenance") or {}).get("sequence") or e.get("sequence")
    if not path:
        return None
    cfg = RunConfig.model_validate({k: v for k, v in rec.items() if k not in RECORD_KEYS})
    return ground_truth_samples(open_sequence(path, reader=cfg.dataset.reader, options=cfg.reader_options()))


def _median_run(g: dict[str, Any]) -> dict[str, Any] | None:
    ok = [e for e in g["ok"] if e["metrics"].get("ate_rmse_cm") is not None]
    if not ok:
        return g["ok"][0] if g["ok"] else None
    ok.sort(key=lambda e: e["metrics"]["ate_rmse_cm"])
    return ok[(len(ok) - 1) // 2]


def _figures(root: Path, seq: str, by_variant: dict[str, dict[str, Any]]) -> list[tuple[str, Path]]:
    """(caption, png) for one sequence: the ATE box plot over seeds and the trajectories on ground truth."""
    from lrslam.pipeline.plots import plot_trajectories
    from lrslam.tools.report_plots import ate_boxplot
    from lrslam.trajectory_io import read_tum

    files = root / FILES_DIR
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", seq)
    figs = []
    ates = {v: [x for _, x in g["per_seed"] if x is not None] for v, g in by_variant.items()}
    if any(ates.values()):
        figs.append(("ATE RMSE over seeds (box: quartiles, triangle: mean, dots: runs)",
                     ate_boxplot(files / f"{safe}_ate_box.png", ates, title=f"{seq}: ATE RMSE over seeds")))
    trajs, gt = {}, None
    for variant, g in by_variant.items():
        e = _median_run(g)
        if e is None:
            continue
        try:
            trajs[f"{variant} (s{e['seed']})"] = read_tum(root / e["run_dir"] / "trajectory.txt")
            if gt is None:
                gt = _ground_truth(root, e)
        except Exception as err:  # a moved sequence or an unreadable file: the plot goes without it
            log.warning("report: %s: %s", e["name"], err)
    if trajs:
        caption = "trajectories (the median-ATE run of each variant)" + (
            ", aligned to the ground truth (SE(3), as the ATE), and their per-frame ATE" if gt is not None
            else "; no ground truth found")
        figs.append((caption, plot_trajectories(files / f"{safe}_trajectories.png", trajs, gt,
                                                title=f"{seq}: trajectories")))
    return figs


# ------------------------------------------------------------------------------------------------ HTML
_STYLE = """body{font-family:sans-serif;margin:2em;max-width:1400px}table{border-collapse:collapse;margin:1em 0}
td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eee}td:first-child,td:nth-child(2)
{text-align:left}img{max-width:100%;border:1px solid #ddd}.failed{color:#b00}figure{margin:1em 0}"""

# Counts the images that failed to load, for tests and for the reader (shown in the page's footer).
_CHECK_SCRIPT = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var broken = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); }).length;
  document.body.setAttribute('data-images', imgs.length);
  document.body.setAttribute('data-broken-images', broken);
  document.getElementById('imgcheck').textContent = imgs.length + ' figures, ' + broken + ' failed to load';
});
</script>"""


def _table(head: list[str], rows: list[list[str]]) -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _img(path: Path) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
    return f'<img alt="{html.escape(Path(path).name)}" src="data:image/png;base64,{data}">'


def _stage_table(by_variant) -> str:
    stages = list(dict.fromkeys(k for g in by_variant.values() for k in g["stages"]))
    rows = [[v] + [_num(g["stages"].get(s), "{:.4f}") for s in stages] + [_num(g["fpt_s"], "{:.3f}")]
            for v, g in by_variant.items()]
    return _table(["variant"] + stages + ["s/frame (wall)"], rows)


def write_report(runs_dir: str | Path, entries: list[dict[str, Any]] | None = None) -> Path:
    """Write ``comparison.md``, ``comparison.csv`` and ``report.html`` (see the module docstring) into
    ``runs_dir``; returns the HTML page's path."""
    root = Path(runs_dir)
    entries = collect_runs(root) if entries is None else entries
    write_tables(root, entries)
    summary = summarise(entries)
    manifest = _read_json(root / "batch.json") or {}
    failed = _failed(entries)
    n_ok = sum(1 for e in entries if e.get("metrics"))
    parts = [f"<h1>lrslam comparison: {html.escape(str(root))}</h1>",
             f"<p>{len(entries)} job(s): {n_ok} finished, {len(failed)} failed."
             + (f" Executor: {html.escape(manifest['executor'])}." if manifest.get("executor") else "")
             + f" Written {datetime.now(timezone.utc).isoformat(timespec='seconds')}."
             " ± is the sample standard deviation over the runs (seeds).</p>",
             _table(HEAD, _rows(summary))]
    for seq, by_variant in summary.items():
        parts.append(f"<h2>{html.escape(seq)}</h2>")
        seq_path = next((e.get("sequence") for g in by_variant.values() for e in g["runs"] if e.get("sequence")), "")
        if seq_path:
            parts.append(f"<p>sequence: <code>{html.escape(str(seq_path))}</code></p>")
        for caption, png in _figures(root, seq, by_variant):
            parts.append(f"<figure>{_img(png)}<figcaption>{html.escape(caption)}</figcaption></figure>")
        parts.append("<h3>frame processing time per stage (s/frame, mean over runs)</h3>" + _stage_table(by_variant))
    if failed:
        parts.append("<h2 class='failed'>failed jobs</h2><ul>" + "".join(
            f"<li class='failed'><code>{html.escape(e['name'])}</code>: {html.escape(str(e['error']))}</li>"
            for e in failed) + "</ul>")
    parts.append("<p><small id='imgcheck'></small></p>")
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>lrslam report</title><style>{_STYLE}</style>"
            f"</head><body>{''.join(parts)}{_CHECK_SCRIPT}</body></html>")
    out = root / "report.html"
    out.write_text(page, encoding="utf-8")
    return out
