"""Compile gsplat's CUDA extension ahead of time, in place, from an installed gsplat wheel.

PyPI's gsplat wheel is pure Python and JIT-compiles its CUDA sources on first use (minutes,
into ~/.cache). On a machine that cannot reach gsplat's prebuilt-wheel index this builds the
same sources once as the module ``gsplat.csrc`` (which gsplat imports before falling back to
JIT), so the result can be kept and reused:

    pip install --target /tmp/site gsplat-1.5.3-py3-none-any.whl
    TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 python tools/gpu/build_gsplat_ext.py /tmp/site/gsplat

It only drives torch's own extension builder (torch.utils.cpp_extension) over gsplat's files.
"""
from __future__ import annotations

import glob
import os
import sys

from setuptools import setup
from torch.utils.cpp_extension import BuildExtension, CUDAExtension


def main(pkg: str) -> None:
    pkg = os.path.abspath(pkg)
    cuda = os.path.join(pkg, "cuda")
    sources = sorted(glob.glob(os.path.join(cuda, "csrc", "*.cu"))
                     + glob.glob(os.path.join(cuda, "csrc", "*.cpp"))) + [os.path.join(cuda, "ext.cpp")]
    ext = CUDAExtension(
        name="gsplat.csrc", sources=sources,
        include_dirs=[os.path.join(cuda, "include"), os.path.join(cuda, "csrc", "third_party", "glm")],
        extra_compile_args={"cxx": ["-O3", "-Wno-attributes"], "nvcc": ["-O3", "-use_fast_math"]})
    build_tmp = os.path.join(os.path.dirname(pkg), "_gsplat_build")
    setup(name="gsplat_ext", ext_modules=[ext], cmdclass={"build_ext": BuildExtension},
          script_args=["build_ext", "--build-lib", os.path.dirname(pkg), "--build-temp", build_tmp])


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: build_gsplat_ext.py PATH/TO/site-packages/gsplat")
    main(sys.argv[1])
