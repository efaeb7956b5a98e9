#!/usr/bin/env bash
# GPU checks and timings on the truck pair, for a GPU machine without network that receives only
# the repository: the CUDA and gsplat tests, one truck training per method on the GPU (HAC, then
# Predict-GS: `-r 4`, `cpu` preset, lambda 0.004, seed 0, device cuda, gsplat), their encode /
# decode / evaluation, and the decoded files' FPS in one process (gsplat, trained size and 4x).
#
# Prepared here, in git-ignored .carry/ (listed in .git/info/exclude):
#   .carry/site.tar.xz   as tools/gpu/device_check.sh describes
#   .carry/truck4/       sparse/ of ../shared/data/tandt_truck and images_4/: the 245x136 uint8
#                        PNGs the CPU runs train on (the scene cache's files, named by image), so
#                        both machines train on the same pixels
# Run there:  bash tools/gpu/device_truck.sh [DEADLINE_S] [ITERATIONS]
# (the comparison is stopped DEADLINE_S seconds after the script started, default 560)
# Resumable: a second run on the same machine continues the comparison in /tmp/truck-gpu.
set -uo pipefail
DEADLINE_S=${1:-560}
start=$(date +%s)
ITERS=${2:-6000}
if ls /tmp/devsite/gsplat/csrc*.so >/dev/null 2>&1; then
    export PYTHONUNBUFFERED=1 OUT=${OUT:-/tmp/pgs-device-out} SITE=/tmp/devsite
    export PYTHONPATH=$SITE:$PWD OMP_NUM_THREADS=$(nproc) NUMBA_NUM_THREADS=$(nproc)
    mkdir -p "$OUT"; t0=$(date +%s); stamp() { echo "[$(( $(date +%s) - t0 )) s] $*"; }
    stamp "gsplat already built on this machine"
else
    source tools/gpu/device_setup.sh
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
    python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)" \
        | tee -a "$OUT/gpu.txt"
    python3 -m pytest -q -rs -p no:cacheprovider tests/test_cuda.py tests/test_render_gsplat.py \
        tests/test_baked.py >"$OUT/cuda-tests.log" 2>&1
    stamp "cuda tests rc=$?"; tail -3 "$OUT/cuda-tests.log"
fi
S=$PWD/.carry/truck4
W=/tmp/truck-gpu
TRAIN_S=$(( DEADLINE_S - ($(date +%s) - start) )); (( TRAIN_S < 10 )) && TRAIN_S=10
timeout "$TRAIN_S" python3 -m baseline.cli compare "$S" -r 4 --patch cpu \
    --set train.device=cuda --set train.rasterizer=auto --set train.iterations="$ITERS" \
    --vs predict-gs --lambda 0.004 --seeds 0 --out "$W" --no-progress --no-plots \
    >>"$OUT/compare.log" 2>&1
rc=$?
stamp "compare rc=$rc (124 = stopped at ${TRAIN_S} s; a second run resumes it)"
tail -4 "$OUT/compare.log"
# each run's training log (time per iteration), whether or not the run finished
for d in "$W"/runs/*/; do
    n=$(basename "$d"); cp "$d/train_log.jsonl" "$OUT/$n.train_log.jsonl" 2>/dev/null
    tail -1 "$d/train_log.jsonl" 2>/dev/null | cut -c1-200
done
if [ $rc -eq 0 ]; then
    cp "$W/report.md" "$W/results.json" "$OUT/"
    files=()
    for f in "$W"/runs/baseline-*/*.pgs "$W"/runs/predict-gs-*/*.pgs; do files+=(--run "$f"); done
    python3 tools/gpu/gpu_fps.py export "${files[1]}" -o /tmp/cams.pt >>"$OUT/fps.log" 2>&1
    python3 tools/gpu/gpu_fps.py bench --cams /tmp/cams.pt "${files[@]}" --device cuda \
        --rounds 10 --scale 1 --scale 4 --json "$OUT/fps.json" >>"$OUT/fps.log" 2>&1
    stamp "fps bench rc=$?"
    grep -v Warning "$OUT/fps.log" | tail -20
fi
