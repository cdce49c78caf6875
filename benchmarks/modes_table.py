"""Rebuild the modes tables (and the promise check) from run folders already on disk, e.g. when only one mode
was re-run: ``python benchmarks/modes_table.py TITLE DIR [DIR ...]`` where each DIR holds ``<variant>/[s<seed>/]
metrics.json`` folders (the layout ``benchmarks/modes.py`` writes); a later DIR's variant replaces an earlier's."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from modes import report  # noqa: E402


def collect(dirs: list[Path]) -> dict[str, dict]:
    """label (``<variant>`` or ``<variant>/s<seed>``) -> metrics, later folders replacing a variant wholesale."""
    by_variant: dict[str, dict[str, dict]] = {}
    for d in dirs:
        found: dict[str, dict[str, dict]] = {}
        for f in sorted(d.glob("*/metrics.json")) + sorted(d.glob("*/s*/metrics.json")):
            rel = f.parent.relative_to(d).as_posix()
            found.setdefault(rel.split("/")[0], {})[rel] = json.loads(f.read_text())
        by_variant |= found
    return {label: m for runs in by_variant.values() for label, m in runs.items()}


if __name__ == "__main__":
    text, ok = report(sys.argv[1], collect([Path(p) for p in sys.argv[2:]]))
    print(text)
    sys.exit(0 if ok else 1)
