#!/usr/bin/env bash
# A second, shorter run after tools/gpu/device_check.sh: rebuild gsplat on a fresh machine,
# rerun the gsplat tests, then the suite from FIRST_FILE on, capped at SECONDS.
# Run there:  bash tools/gpu/device_rerun.sh FIRST_FILE SECONDS
set -uo pipefail
source tools/gpu/device_setup.sh
python3 -m pytest -q -rs -p no:cacheprovider tests/test_render_gsplat.py >"$OUT/gsplat-tests.log" 2>&1
stamp "gsplat tests rc=$?"; tail -3 "$OUT/gsplat-tests.log"
files=$(ls tests/test_*.py | awk -v f="$1" '$0 >= f')
timeout "$2" python3 -m pytest -q -rs -p no:cacheprovider $files >"$OUT/suite2.log" 2>&1
stamp "suite from $1 rc=$? (124 = stopped)"; tail -15 "$OUT/suite2.log"
