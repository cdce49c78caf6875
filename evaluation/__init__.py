"""Evaluation (reads ground truth; algorithm code never imports this)."""
