#!/usr/bin/env bash
# One-shot installer used by `make install` (and so by `make test` / `make demo`):
# 1. system libraries open3d needs (libusb-1.0-0, libgomp1), via apt-get when missing and possible;
# 2. a virtualenv in $VENV (default .venv) with torch (CPU build pinned, override with TORCH_SPEC);
# 3. this project, editable, with its test extras.
set -euo pipefail
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}

need_libs=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || need_libs+=(libusb-1.0-0)
ldconfig -p 2>/dev/null | grep -q 'libgomp.so.1' || need_libs+=(libgomp1)
if [ ${#need_libs[@]} -gt 0 ]; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
  if command -v apt-get >/dev/null && { [ "$(id -u)" -eq 0 ] || [ -n "$SUDO" ]; }; then
    echo "[install] apt-get install ${need_libs[*]}"
    $SUDO apt-get update -qq || true
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_libs[@]}" >/dev/null
  else
    echo "[install] WARNING: missing system libraries ${need_libs[*]} (open3d needs them); install them with your package manager" >&2
  fi
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "[install] creating virtualenv $VENV"
  "$PYTHON" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q "$TORCH_SPEC"
"$VENV/bin/python" -m pip install -q -e ".[test]"
"$VENV/bin/python" -c "import open3d, gtsam, kiss_icp, torch, lrslam.field, lrslam.frontend, lrslam.backend, lrslam.pipeline; print('[install] ok: torch', torch.__version__, '| open3d', open3d.__version__, '| cuda', torch.cuda.is_available())"
# compile the numba CPU kernels once (cached on disk), so the first run and the tests do not pay for it
"$VENV/bin/python" -c "from lrslam.field.cpu_ops import warm_up; print('[install] numba kernels:', 'compiled' if warm_up() else 'unavailable, torch kernels in use')"
