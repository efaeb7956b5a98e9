#!/usr/bin/env bash
# One-command set-up and run. Creates ./.venv on first use, installs PyTorch and the project in
# editable mode (the test extras only for `test`), then:
#   ./run.sh demo      the main job on the embedded default scene (~10 min on 2 cores)
#   ./run.sh test      the test suite, on every core (pytest-xdist, one thread per worker)
#   ./run.sh lint      ruff check, then mypy on the typed boundary (both set in pyproject.toml)
#   ./run.sh pgs ARGS  any pgs command inside the environment
#
# PyTorch comes from the package index pip is configured with, nothing else is contacted:
#   PGS_TORCH        the requirement to install (default torch==2.13.0; the project accepts
#                    >=2.1,<2.14)
#   PGS_TORCH_INDEX  a wheel index for it, e.g. https://download.pytorch.org/whl/cpu for the CPU
#                    build or https://download.pytorch.org/whl/cu121 for CUDA 12.1 (PyPI's
#                    torch for Linux x86-64 is a CUDA build of several GB)
set -euo pipefail
cd "$(dirname "$0")"
usage() {
  echo "usage: ./run.sh demo [pgs demo options]   the main job (HAC vs Predict-GS on the embedded scene)" >&2
  echo "       ./run.sh test [pytest options]     the test suite (on every core)" >&2
  echo "       ./run.sh lint                      ruff check, then mypy" >&2
  echo "       ./run.sh pgs ARGS...               any pgs command in ./.venv" >&2
}
cmd=${1:-}
case "$cmd" in
  demo|test|lint|pgs) shift ;;
  -h|--help) usage; exit 0 ;;
  *) usage; exit 2 ;;
esac
VENV=.venv
PY=${PYTHON:-python3}
TORCH=${PGS_TORCH:-torch==2.13.0}
extras=""
case "$cmd" in test|lint) extras="[test]" ;; esac
stamp_for() { (cat pyproject.toml; echo "$TORCH ${PGS_TORCH_INDEX:-} $1") | sha1sum | cut -c1-12; }
if [ ! -f "$VENV/.installed-$(stamp_for "$extras")" ]; then
  echo "[run.sh] setting up $VENV (first run only)..."
  [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
  "$VENV/bin/pip" install -q --upgrade pip >/dev/null 2>&1 || true
  # torch first: with it installed, the project's torch range resolves to it (no other build)
  if [ -n "${PGS_TORCH_INDEX:-}" ]; then
    "$VENV/bin/pip" install -q --index-url "$PGS_TORCH_INDEX" "$TORCH"
  else
    "$VENV/bin/pip" install -q "$TORCH"
  fi
  "$VENV/bin/pip" install -q -e ".$extras"
  "$VENV/bin/python" -c "import torch; print('[run.sh] PyTorch', torch.__version__, '(CUDA ' + (torch.version.cuda or 'none: the CPU build') + ')')"
  # compile the CPU kernels into numba's disk cache once, here, not in the first training
  "$VENV/bin/pgs" warmup || echo "[run.sh] kernel warm-up failed: the first training compiles them"
  rm -f "$VENV"/.installed-*
  touch "$VENV/.installed-$(stamp_for "$extras")"
  # the test environment holds everything the demo needs
  if [ -n "$extras" ]; then touch "$VENV/.installed-$(stamp_for "")"; fi
fi
# One thread per core, never more (oversubscription was measured 5x slower): the test suite
# runs one pytest-xdist worker per core, each with one thread.
if [ "$cmd" = test ]; then
  export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
  export NUMBA_NUM_THREADS=${NUMBA_NUM_THREADS:-1}
fi
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-$(nproc)}
export NUMBA_NUM_THREADS=${NUMBA_NUM_THREADS:-$(nproc)}
# torch's OpenMP workers spin after each op and steal the cores from the numba kernels that
# run next (measured 20-40% slower kernels): let them sleep instead.
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-PASSIVE}
case "$cmd" in
  demo) exec "$VENV/bin/pgs" demo "$@" ;;
  test) exec "$VENV/bin/python" -m pytest -q -n auto "$@" ;;
  lint) "$VENV/bin/ruff" check . && exec "$VENV/bin/mypy" ;;
  pgs)  exec "$VENV/bin/pgs" "$@" ;;
esac
