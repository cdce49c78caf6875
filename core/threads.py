"""CPU threads of a run: how many (one call sets every library's pool, so batch jobs can be pinned) and their
floating-point mode.

Torch's intra-op pool and numba (:mod:`lrslam.field.cpu_ops` follows torch's count before each kernel) follow
:func:`set_threads` at once; OpenMP libraries (Open3D, BLAS) read ``OMP_NUM_THREADS`` when they load, so the
variable is set too and takes effect for them only when called before they are imported (the CLI does).

:func:`flush_denormals` makes the CPU flush subnormal float results to zero. The field's backward passes meet many of
them (the gradient of a sample far from the surface through the SDF-to-weight sigmoid is ~1e-40), and x86 CPUs
take ~100x longer on a subnormal operand or result: on the TUM excerpt 2-3 % of the gradient values reaching the
CP lines in a mapping step were subnormal and the CP backward kernel ran 2.7x slower than on the same data
flushed (a fused run: 0.695 -> 0.586 s/frame, the same trajectory). The mode is
per thread and a thread inherits it from the thread that starts it, so it is set before any pool starts: by the
CLI first thing, by :func:`lrslam.pipeline.run.run_sequence` and by a new :class:`lrslam.Slam` (a pool that an
application started earlier keeps its own mode).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform
import struct

from lrslam.errors import InputError

__all__ = ["set_threads", "flush_denormals"]

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


def flush_denormals() -> bool:
    """Flush subnormal float results to zero (x86 MXCSR's FTZ bit) in the calling thread and in every thread it
    starts from now on. A subnormal is below 1.2e-38 in float32 (2.2e-308 in float64): only results that small
    change, to 0 (the TUM excerpt's fused trajectory is the same to the last digit, and 1.2x faster).

    Only FTZ: subnormal *inputs* keep their value (no DAZ, which torch's ``set_flush_denormal`` also sets), so
    code that steps to the next float by hand still works: scipy's cKDTree recursed without end (a segfault) on
    a planar mesh's points with DAZ on. Set through glibc's ``fegetenv`` / ``fesetenv`` (the SSE control word is
    the last field of x86-64's ``fenv_t``) and checked on a product of two tiny floats; elsewhere (another CPU
    or C library) nothing changes. Returns whether the mode is on."""
    if _product_of_tiny() == 0.0:
        return True
    if platform.system() != "Linux" or platform.machine() not in ("x86_64", "AMD64"):
        return False
    try:
        libm = ctypes.CDLL(ctypes.util.find_library("m") or "libm.so.6")
        env = ctypes.create_string_buffer(_FENV_SIZE)
        if libm.fegetenv(env) != 0:
            return False
        before = bytes(env.raw)
        mxcsr = struct.unpack_from("<I", before, _MXCSR_OFFSET)[0]
        if mxcsr > 0xFFFF:   # reserved bits set: not an SSE control word (loading it would fault); leave it
            return False
        raw = bytearray(before)
        struct.pack_into("<I", raw, _MXCSR_OFFSET, mxcsr | _MXCSR_FTZ)
        if libm.fesetenv(ctypes.create_string_buffer(bytes(raw), _FENV_SIZE)) != 0:
            return False
        if _product_of_tiny() != 0.0:   # did not take: restore what was there
            libm.fesetenv(ctypes.create_string_buffer(before, _FENV_SIZE))
            return False
    except (OSError, AttributeError):
        return False
    return True


_FENV_SIZE = 32          # sizeof(fenv_t) on x86-64 glibc / musl (x87 environment, then the SSE control word)
_MXCSR_OFFSET = 28
_MXCSR_FTZ = 0x8000


def _product_of_tiny() -> float:
    """1e-20 * 1e-20 in float32 on this thread: 1e-40 (a subnormal) normally, 0.0 with FTZ."""
    import numpy as np

    return float(np.float32(1e-20) * np.float32(1e-20))
