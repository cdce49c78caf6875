"""JSON the project writes is strict JSON: no ``Infinity`` / ``NaN`` (which ``json.dumps`` emits by default).

:func:`json_safe` replaces a non-finite float by ``None`` and, inside a mapping, adds ``"<key>_reason"``
saying what the value was; :func:`dumps` applies it and refuses anything still not strict JSON.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

__all__ = ["json_safe", "dumps"]


def _reason(x: float) -> str:
    return "not a number (NaN)" if math.isnan(x) else f"{'+' if x > 0 else '-'}infinite"


def _scalar(x: Any) -> Any:
    if isinstance(x, np.generic):
        x = x.item()
    return x


def json_safe(obj: Any) -> Any:
    """A copy of ``obj`` (dicts, lists, tuples, numpy arrays and scalars) where every non-finite float is None.

    In a dict, ``{"acc": inf}`` becomes ``{"acc": None, "acc_reason": "+infinite"}`` (an existing
    ``acc_reason`` key is kept). Numpy arrays become lists, numpy scalars Python numbers.
    """
    obj = _scalar(obj)
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        out: dict[str, Any] = {}
        for k, v in obj.items():
            v = _scalar(v)
            out[k] = json_safe(v)
            if isinstance(v, float) and not math.isfinite(v) and f"{k}_reason" not in obj:
                out[f"{k}_reason"] = _reason(v)
        return out
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def dumps(obj: Any, **kwargs: Any) -> str:
    """``json.dumps(json_safe(obj), allow_nan=False, **kwargs)``: always strict JSON."""
    return json.dumps(json_safe(obj), allow_nan=False, **kwargs)
