#!/usr/bin/env bash
# A second, shorter device call after tools/device_check.sh: rebuild gsplat on the fresh machine,
# rerun the gsplat tests, then the suite from FIRST_FILE on, capped at SECONDS.
# Run there:  bash tools/device_rerun.sh FIRST_FILE SECONDS
set -uo pipefail
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/pgs-device-out}; mkdir -p "$OUT"
t0=$(date +%s); stamp() { echo "[$(( $(date +%s) - t0 )) s] $*"; }
tar -xJf .carry/site.tar.xz -C /tmp || exit 1
SITE=/tmp/devsite; d=$SITE/predict_gs_toolkit-0.1.0.dist-info; mkdir -p "$d"
printf 'Metadata-Version: 2.1\nName: predict-gs-toolkit\nVersion: 0.1.0\n' >"$d/METADATA"
printf '[pgs.plugins]\npredict = predict_plugin:register\n' >"$d/entry_points.txt"
export PYTHONPATH=$SITE:$PWD OMP_NUM_THREADS=$(nproc) NUMBA_NUM_THREADS=$(nproc)
TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=$(nproc) python3 tools/build_gsplat_ext.py $SITE/gsplat >"$OUT/build.log" 2>&1
stamp "gsplat build rc=$?"
python3 -m pytest -q -rs -p no:cacheprovider tests/test_render_gsplat.py >"$OUT/gsplat-tests.log" 2>&1
stamp "gsplat tests rc=$?"; tail -3 "$OUT/gsplat-tests.log"
files=$(ls tests/test_*.py | awk -v f="$1" '$0 >= f')
timeout "$2" python3 -m pytest -q -rs -p no:cacheprovider $files >"$OUT/suite2.log" 2>&1
stamp "suite from $1 rc=$? (124 = stopped)"; tail -15 "$OUT/suite2.log"
