"""``lrslam report``: the tables (mean ± std over seeds), the HTML page opened in a real headless Chromium (every
image present; the check fails on a broken image), reports of run folders without a batch manifest, and evo's
``evo_ape tum groundtruth.txt trajectory.txt -a`` agreeing with the ATE in a run folder's metrics.json."""

from __future__ import annotations

import csv
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from lrslam.tools.report import collect_runs, summarise, write_report

CHROMIUM = Path("/usr/bin/chromium")
needs_chromium = pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is absent (scripts/install.sh "
                                                                  "installs the Debian package chromium)")


def browser_image_check(page: Path) -> tuple[int, int]:
    """Open ``page`` in headless Chromium; return (images, images that failed to load) as counted by the page's
    own script once it has loaded."""
    with tempfile.TemporaryDirectory() as profile:
        r = subprocess.run([str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                            "--no-first-run", "--disable-background-networking", "--disable-component-update",
                            "--disable-sync", f"--user-data-dir={profile}", "--virtual-time-budget=5000",
                            "--dump-dom", page.resolve().as_uri()], capture_output=True, text=True, timeout=120)
    body = re.search(r"<body[^>]*>", r.stdout)
    assert body, f"no DOM from chromium (exit {r.returncode}): {r.stderr[-500:]}"
    n = re.search(r'data-images="(\d+)"', body.group(0))
    broken = re.search(r'data-broken-images="(\d+)"', body.group(0))
    assert n and broken, f"the page's image check did not run: {body.group(0)}"
    return int(n.group(1)), int(broken.group(1))


def test_tables_give_mean_and_std_over_seeds(tiny_batch):
    out = tiny_batch["out"]
    entries = collect_runs(out)
    s = summarise(entries)
    g = s["a-room"]["field"]
    ates = [json.loads((out / f"a-room/field/s{k}/metrics.json").read_text())["ate_rmse_cm"] for k in (0, 1)]
    assert g["ate_rmse"][0] == pytest.approx(np.mean(ates)) and g["ate_rmse"][1] == pytest.approx(np.std(ates, ddof=1))
    assert [seed for seed, _ in g["per_seed"]] == [0, 1] and g["parameters"]["total"] > 0
    assert "map" in g["stages"] and "refine" in g["stages"]
    rows = list(csv.DictReader((out / "comparison.csv").open()))
    row = next(r for r in rows if r["sequence"] == "a-room" and r["variant"] == "field")
    assert float(row["ate_rmse_cm_mean"]) == pytest.approx(np.mean(ates)) and row["runs_ok"] == "2"
    assert next(r for r in rows if r["sequence"] == "bad-room" and r["variant"] == "field")["runs_failed"] == "2"
    md = (out / "comparison.md").read_text()
    assert f"| a-room | field | 2/2 | {np.mean(ates):.2f} ± {np.std(ates, ddof=1):.2f} |" in md


@needs_chromium
def test_report_opens_in_chromium_with_every_image(tiny_batch, tmp_path):
    page = tiny_batch["out"] / "report.html"
    text = page.read_text()
    assert "bad-room/field/s0" in text and "frame processing time per stage" in text
    n, broken = browser_image_check(page)
    # per sequence with runs: the ATE box plot and the trajectories on ground truth (bad-room has no runs)
    assert n == 4 and broken == 0
    # the check can fail: the same page with one image broken
    bad = tmp_path / "broken.html"
    bad.write_text(text.replace('src="data:image/png;base64,', 'src="data:image/png;base64,AAAA', 1))
    assert browser_image_check(bad) == (4, 1)


def test_report_of_run_folders_without_a_manifest(tiny_batch, tmp_path):
    runs = tmp_path / "runs"
    shutil.copytree(tiny_batch["out"], runs, ignore=shutil.ignore_patterns("batch.json", "report*", "comparison*"))
    r = subprocess.run([sys.executable, "-m", "lrslam", "report", str(runs)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-1000:]
    assert (runs / "report.html").is_file() and (runs / "comparison.csv").is_file()
    md = (runs / "comparison.md").read_text()
    # found from config.yaml: sequence (named as in the batch: a/room, b/room, bad/room), mode and seed
    assert "| a-room | field | 2/2 |" in md and "| b-room | frontend | 1/1 |" in md
    assert "| bad-room | field | 0/2 (2 failed) |" in md
    assert "Failed jobs:" in md and "corrupt image" in md
    r = subprocess.run([sys.executable, "-m", "lrslam", "report", str(tmp_path / "nothing")], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith("error:") and "nothing" in r.stderr


def test_evo_ape_gives_the_run_folders_ate(tiny_batch):
    evo_ape = Path(sys.executable).with_name("evo_ape")
    if not evo_ape.exists():
        pytest.skip("evo is not installed (the test extra)")
    run = tiny_batch["out"] / "a-room" / "field" / "s1"
    gt = tiny_batch["seqs"]["a"] / "groundtruth.txt"
    r = subprocess.run([str(evo_ape), "tum", str(gt), str(run / "trajectory.txt"), "-a", "--no_warnings"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-1000:]
    rmse_m = float(re.search(r"^\s*rmse\s+([0-9.eE+-]+)", r.stdout, re.M).group(1))
    ours = json.loads((run / "metrics.json").read_text())["ate_rmse_cm"]
    assert ours == pytest.approx(100.0 * rmse_m, abs=1e-4)
