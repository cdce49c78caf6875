"""CPU thread count of a run: one call sets every library's pool, so batch jobs can be pinned.

Torch's intra-op pool and numba (:mod:`lrslam.field.cpu_ops` follows torch's count before each kernel) follow
:func:`set_threads` at once; OpenMP libraries (Open3D, BLAS) read ``OMP_NUM_THREADS`` when they load, so the
variable is set too and takes effect for them only when called before they are imported (the CLI does).
"""

from __future__ import annotations

import os

from lrslam.errors import InputError

__all__ = ["set_threads"]

_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


def set_threads(n: int | None) -> int | None:
    """Use ``n`` CPU threads (None: leave every library's default). Returns ``n``.
    Raises InputError for ``n < 1``."""
    if n is None:
        return None
    if int(n) < 1:
        raise InputError(f"--threads must be >= 1, got {n}")
    n = int(n)
    for key in _ENV:
        os.environ[key] = str(n)
    import torch

    torch.set_num_threads(n)
    return n
