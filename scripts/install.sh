#!/usr/bin/env bash
# One-shot installer used by `make install` (and so by `make test` / `make demo`):
# 1. system libraries open3d needs (libusb-1.0-0, libgomp1), via apt-get when missing and possible, and
#    Chromium (the report test opens `lrslam report` pages in headless Chromium; skipped when it cannot be had);
# 2. a virtualenv in $VENV (default .venv) with torch (CPU build pinned, override with TORCH_SPEC);
# 3. this project, editable, with its test, distributed (Ray) and viewer (Rerun) extras.
set -euo pipefail
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}

need_libs=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || need_libs+=(libusb-1.0-0)
ldconfig -p 2>/dev/null | grep -q 'libgomp.so.1' || need_libs+=(libgomp1)
SUDO=""
[ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
can_apt=0
command -v apt-get >/dev/null && { [ "$(id -u)" -eq 0 ] || [ -n "$SUDO" ]; } && can_apt=1
apt_updated=0
apt_install() {  # apt_install PKG... (one apt-get update per install run)
  [ "$apt_updated" -eq 1 ] || { $SUDO apt-get update -qq || true; apt_updated=1; }
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}
if [ ${#need_libs[@]} -gt 0 ]; then
  if [ "$can_apt" -eq 1 ]; then
    echo "[install] apt-get install ${need_libs[*]}"
    apt_install "${need_libs[@]}"
  else
    echo "[install] WARNING: missing system libraries ${need_libs[*]} (open3d needs them); install them with your package manager" >&2
  fi
fi
# Chromium is optional (only the report test uses it): a failure here is a warning, never a failed install.
if [ ! -x /usr/bin/chromium ] && [ "${LRSLAM_NO_CHROMIUM:-0}" = "0" ]; then
  if [ "$can_apt" -eq 1 ]; then
    echo "[install] apt-get install chromium (headless report test)"
    apt_install chromium || echo "[install] WARNING: chromium could not be installed; the report browser test will skip" >&2
  else
    echo "[install] note: /usr/bin/chromium absent; the report browser test will skip" >&2
  fi
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "[install] creating virtualenv $VENV"
  "$PYTHON" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q "$TORCH_SPEC"
"$VENV/bin/python" -m pip install -q -e ".[test,distributed,viewer]"
"$VENV/bin/python" -c "import open3d, gtsam, kiss_icp, torch, lrslam.field, lrslam.frontend, lrslam.backend, lrslam.pipeline, ray, rerun; print('[install] ok: torch', torch.__version__, '| open3d', open3d.__version__, '| ray', ray.__version__, '| rerun', rerun.__version__, '| cuda', torch.cuda.is_available())"
# compile the numba CPU kernels once (cached on disk), so the first run and the tests do not pay for it
"$VENV/bin/python" -c "from lrslam.field.cpu_ops import warm_up; print('[install] numba kernels:', 'compiled' if warm_up() else 'unavailable, torch kernels in use')"
