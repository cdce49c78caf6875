"""``benchmarks/paper.py --smoke`` runs every section and writes RESULTS.md with its plots (slow: ~2 minutes)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_paper_smoke_writes_the_document(tmp_path):
    docs = tmp_path / "docs"
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "paper.py"), "--smoke", "--docs", str(docs),
                          "--work", str(tmp_path / "work")], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    text = (docs / "RESULTS.md").read_text()
    for heading in ("## 1. Table 1", "## 2. Memory growth", "## 3. Ablation", "## 4. Depth-noise", "## 5. Convergence"):
        assert heading in text
    assert "All parameter counts agree with the paper to its rounding." in text
    for png in ("paper_memory.png", "paper_ablation.png", "paper_convergence.png"):
        assert (docs / png).stat().st_size > 1000
