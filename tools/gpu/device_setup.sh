# Sourced by tools/gpu/device_check.sh and tools/gpu/device_rerun.sh on the GPU machine: unpack the
# carried installs (.carry/site.tar.xz, see device_check.sh), register the project's entry
# points, build gsplat's CUDA extension. Sets OUT, SITE, PYTHONPATH, thread counts, stamp().
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/pgs-device-out}
mkdir -p "$OUT"
t0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - t0 )) s] $*"; }

tar -xJf .carry/site.tar.xz -C /tmp || exit 1
SITE=/tmp/devsite
# The project itself, registered for importlib.metadata (its plugin is an entry point).
d=$SITE/predict_gs_toolkit-0.1.0.dist-info
mkdir -p "$d"
printf 'Metadata-Version: 2.1\nName: predict-gs-toolkit\nVersion: 0.1.0\n' >"$d/METADATA"
printf '[pgs.plugins]\npredict = predict_plugin:register\n\n[console_scripts]\npgs = baseline.cli:main\n' \
    >"$d/entry_points.txt"
export PYTHONPATH=$SITE:$PWD
export OMP_NUM_THREADS=$(nproc) NUMBA_NUM_THREADS=$(nproc)
stamp "unpacked"

# gsplat's CUDA extension, ahead of time (its wheel would JIT-compile on first use)
TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=$(nproc) python3 tools/gpu/build_gsplat_ext.py $SITE/gsplat \
    >"$OUT/build.log" 2>&1
stamp "gsplat build rc=$?"
