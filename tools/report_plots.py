"""Report figures (PNG, matplotlib Agg; no pyplot global state): ATE box plots over seeds."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["ate_boxplot"]


def ate_boxplot(path_png: str | Path, ates: dict[str, list[float]], title: str = "") -> Path:
    """Box plot of ATE RMSE (cm) per variant over its runs (seeds), each run drawn as a dot; writes the PNG.

    ``ates``: variant -> ATE RMSE of each of its runs, cm (a variant with no value is drawn empty)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    names = list(ates)
    fig = Figure(figsize=(max(4.0, 1.3 * len(names) + 1.5), 4.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    data = [np.asarray(ates[n], dtype=float) for n in names]
    ax.boxplot([d if len(d) else [np.nan] for d in data], showmeans=True)
    ax.set_xticks(range(1, len(names) + 1), names, rotation=20 if len(names) > 4 else 0)
    rng = np.random.default_rng(0)   # fixed jitter: the figure is reproducible
    for i, d in enumerate(data, start=1):
        ax.plot(i + rng.uniform(-0.08, 0.08, len(d)), d, "o", ms=4, alpha=0.7, color="k")
    ax.set_ylabel("ATE RMSE [cm]")
    ax.grid(axis="y", alpha=0.3)
    ax.set_title(title or "ATE RMSE over seeds")
    fig.tight_layout()
    path = Path(path_png)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
