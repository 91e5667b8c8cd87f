"""Builds torchvor._C against the torch that is already installed.

Switches (environment variables):
  TORCHVOR_FORCE_CPU=1   build without CUDA even if torch and nvcc support it
  TORCHVOR_FORCE_CUDA=1  build the CUDA sources or fail with the reason
  TORCH_CUDA_ARCH_LIST   GPU architectures, e.g. "9.0" (torch's own variable)
"""
import glob
import os
import sys

from setuptools import find_packages, setup

try:
    import torch
    from torch.utils import cpp_extension
except ImportError:
    sys.exit(
        "torchvor is built against the torch you have installed, and none was found.\n"
        "Install torch first, then build without isolation:\n"
        "    pip install torch==2.13.0\n"
        "    pip install --no-build-isolation .\n"
        "(or run `bash scripts/test.sh`, which does both)."
    )


def flag(name):
    return os.environ.get(name, "0").lower() in ("1", "true", "yes", "on")


def want_cuda():
    if flag("TORCHVOR_FORCE_CPU"):
        return False
    has_cuda_torch = torch.version.cuda is not None
    has_nvcc = cpp_extension.CUDA_HOME is not None
    if flag("TORCHVOR_FORCE_CUDA"):
        if not has_cuda_torch:
            sys.exit(f"TORCHVOR_FORCE_CUDA=1 but torch {torch.__version__} is a CPU-only build")
        if not has_nvcc:
            sys.exit("TORCHVOR_FORCE_CUDA=1 but nvcc was not found (set CUDA_HOME)")
        return True
    return has_cuda_torch and has_nvcc


def extension():
    here = os.path.dirname(os.path.abspath(__file__))
    sources = [os.path.relpath(p, here) for p in sorted(glob.glob(os.path.join(here, "csrc", "*.cpp")))]
    for folder in ("ops", "cpu"):
        sources += [os.path.relpath(p, here) for p in sorted(glob.glob(os.path.join(here, "csrc", folder, "*.cpp")))]
    # -fopenmp on compile and link: without it at::parallel_for silently runs on one thread.
    cxx = ["-O3", "-std=c++17", "-fopenmp", "-g0"]
    link = ["-fopenmp"]
    if not want_cuda():
        print("torchvor: building the CPU backend only")
        return cpp_extension.CppExtension(
            "torchvor._C", sources, extra_compile_args={"cxx": cxx}, extra_link_args=link
        )
    print("torchvor: building the CPU and CUDA backends")
    sources += [os.path.relpath(p, here) for p in sorted(glob.glob(os.path.join(here, "csrc", "cuda", "*.cu")))]
    nvcc = ["-O3", "-std=c++17", "-lineinfo", "--expt-relaxed-constexpr"]
    return cpp_extension.CUDAExtension(
        "torchvor._C", sources, extra_compile_args={"cxx": cxx, "nvcc": nvcc}, extra_link_args=link
    )


setup(
    packages=find_packages(include=["torchvor", "torchvor.*"]),
    ext_modules=[extension()],
    cmdclass={"build_ext": cpp_extension.BuildExtension},
)
