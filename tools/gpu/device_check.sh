#!/usr/bin/env bash
# The GPU checks in one script, for a GPU machine without network that receives only the
# repository (see README, "GPU checks on a machine without network").
#
# Prepared here, in git-ignored .carry/ (listed in .git/info/exclude):
#   .carry/site.tar.xz        cp312 x86-64 installs of gsplat, constriction, pycolmap,
#                             OpenImageIO, tomli-w (pip install --target ... --python-version
#                             3.12, tarred under devsite/); the machine has torch, numba, scipy,
#                             scikit-image, pytest and hypothesis
#   .carry/models/*.pgs       decoded-model files to time (first = the reference of the ratios)
#   .carry/cams.pt            their test cameras (python tools/gpu/gpu_fps.py export FILE -o ...)
# Run there:  bash tools/gpu/device_check.sh [SECONDS_FOR_THE_FULL_SUITE]
set -uo pipefail
SUITE_S=${1:-150}
source tools/gpu/device_setup.sh
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)" \
    | tee -a "$OUT/gpu.txt"
nproc | tee -a "$OUT/gpu.txt"
python3 -c "from gsplat import csrc; import gsplat; print('gsplat', gsplat.__version__, csrc.__file__)" \
    2>&1 | tail -2

# the CUDA tests (skipped on the CPU machine) and the gsplat rasterizer tests
python3 -m pytest -q -rs -p no:cacheprovider tests/test_cuda.py tests/test_render_gsplat.py \
    tests/test_baked.py \
    >"$OUT/cuda-tests.log" 2>&1
stamp "cuda tests rc=$?"
tail -5 "$OUT/cuda-tests.log"

# decoded-model FPS, one process, rotated rounds; at the trained size and at 4x
runs=()
for f in .carry/models/*.pgs; do runs+=(--run "$f"); done
if [ ${#runs[@]} -gt 0 ] && [ -f .carry/cams.pt ]; then
    python3 tools/gpu/gpu_fps.py bench --cams .carry/cams.pt "${runs[@]}" --device cuda \
        --rounds 10 --scale 1 --scale 4 --json "$OUT/fps.json" >"$OUT/fps.log" 2>&1
    stamp "fps bench rc=$?"
fi

# the whole suite with the GPU present (tests with device 'auto' take the CUDA path), capped;
# SECONDS_FOR_THE_FULL_SUITE 0 skips it
if [ "$SUITE_S" -gt 0 ]; then
    timeout "$SUITE_S" python3 -m pytest -q -p no:cacheprovider -x tests >"$OUT/suite.log" 2>&1
    stamp "full suite rc=$? (124 = stopped at ${SUITE_S} s)"
    tail -3 "$OUT/suite.log"
fi
echo "==== fps"
cat "$OUT/fps.log" 2>/dev/null | grep -v Warning
