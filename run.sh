#!/usr/bin/env bash
# One-command set-up and run. Creates ./.venv on first use (CPU PyTorch pinned to 2.13.0, so no
# CUDA packages are pulled), installs the project in editable mode, then:
#   ./run.sh demo      the main job on the embedded default scene
#   ./run.sh test      the test suite
#   ./run.sh pgs ARGS  any pgs command inside the environment
set -euo pipefail
cd "$(dirname "$0")"
VENV=.venv
PY=${PYTHON:-python3}
stamp="$VENV/.installed-$(sha1sum pyproject.toml | cut -c1-12)"
if [ ! -f "$stamp" ]; then
  echo "[run.sh] setting up $VENV (first run only)..."
  [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
  "$VENV/bin/pip" install -q --upgrade pip >/dev/null 2>&1 || true
  # CPU wheel first: with torch 2.13.0 present the project's torch range resolves to it.
  "$VENV/bin/pip" install -q "torch==2.13.0"
  "$VENV/bin/pip" install -q -e ".[test]"
  rm -f "$VENV"/.installed-*
  touch "$stamp"
fi
# Two cores here: one thread per core, never more (oversubscription was measured 5x slower).
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-$(nproc)}
export NUMBA_NUM_THREADS=${NUMBA_NUM_THREADS:-$(nproc)}
# torch's OpenMP workers spin after each op and steal the cores from the numba kernels that
# run next (measured 20-40% slower kernels): let them sleep instead.
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-PASSIVE}
cmd=${1:-demo}; shift || true
case "$cmd" in
  demo) exec "$VENV/bin/pgs" demo "$@" ;;
  test) exec "$VENV/bin/python" -m pytest -q "$@" ;;
  pgs)  exec "$VENV/bin/pgs" "$@" ;;
  *) echo "usage: ./run.sh [demo|test|pgs ARGS...]" >&2; exit 2 ;;
esac
