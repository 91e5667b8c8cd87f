"""Builds torchvor._C against the torch that is already installed.

Where torch cannot be imported (none is installed, or pip's isolated build
environment hides the installed one), it stops at once with the command to
run instead: torchvor._C only works with the torch it was compiled against.

Switches (environment variables):
  TORCHVOR_FORCE_CPU=1   build without CUDA even if torch and nvcc support it
  TORCHVOR_FORCE_CUDA=1  build the CUDA sources or fail with the reason
  TORCH_CUDA_ARCH_LIST   GPU architectures, e.g. "9.0" (torch's own variable)
"""
import glob
import os
import re
import shlex
import shutil
import subprocess
import sys

TORCH_PIN = "torch==2.13.0"  # pinned in the advice: an unpinned torch pulls the newest CUDA build (GBs)


def _process_argv(pid):
    """argv of a process (Linux /proc), or None."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as handle:
            return [part.decode(errors="replace") for part in handle.read().split(b"\0") if part]
    except OSError:
        return None


def _parent_python():
    """(python, argv) of the process that started this build when it is a Python
    (pip: a frontend runs the build backend as its child), else (None, argv or None)."""
    argv = _process_argv(os.getppid())
    if not argv or not re.fullmatch(r"(python|pypy)[0-9.]*(\.exe)?", os.path.basename(argv[0])):
        return None, argv
    python = argv[0]
    if os.sep not in python:  # found on the parent's PATH
        try:
            with open(f"/proc/{os.getppid()}/environ", "rb") as handle:
                entries = dict(item.split(b"=", 1) for item in handle.read().split(b"\0") if b"=" in item)
            path = entries.get(b"PATH", b"").decode(errors="replace")
        except OSError:
            path = os.environ.get("PATH", "")
        python = shutil.which(python, path=path)
    elif not os.path.isabs(python):
        try:
            python = os.path.join(os.readlink(f"/proc/{os.getppid()}/cwd"), python)
        except OSError:
            python = os.path.abspath(python)
    return python, argv


def _torch_of(python):
    """(torch version, sys.prefix) of the torch that ``python`` imports outside any build environment."""
    environment = {name: value for name, value in os.environ.items()
                   if name not in ("PYTHONPATH", "PYTHONNOUSERSITE", "PYTHONHOME", "PYTHONSAFEPATH")
                   and not name.startswith("PIP_BUILD")}
    try:
        result = subprocess.run(
            [python, "-c", "import sys, torch; print(torch.__version__); print(sys.prefix)"],
            capture_output=True, text=True, timeout=120, env=environment)
    except (OSError, subprocess.SubprocessError):
        return None
    lines = result.stdout.strip().splitlines()
    return (lines[0], lines[1]) if result.returncode == 0 and len(lines) == 2 else None


def _pip_command(argv):
    """The pip command that started this build with --no-build-isolation added, else the generic one."""
    generic = "pip install --no-build-isolation ."
    if not argv:
        return generic
    words = argv[1:]
    if words[:2] == ["-m", "pip"]:
        words = words[2:]
    elif words and os.path.basename(words[0]).startswith("pip"):
        words = words[1:]
    else:
        return generic
    if "--no-build-isolation" in words:
        return shlex.join(["pip", *words])
    for position, word in enumerate(words):
        if word in ("install", "wheel", "download"):
            return shlex.join(["pip", *words[:position + 1], "--no-build-isolation", *words[position + 1:]])
    return generic


def _no_torch_message():
    """Why torch cannot be imported here, and the command that fixes it."""
    # pip isolates a build in a virtual environment of its own (recent pip), or
    # (older pip) by hiding site-packages behind a sitecustomize on PYTHONPATH.
    build_env = sys.prefix if "pip-build-env-" in sys.prefix else next(
        (os.path.dirname(entry) for entry in os.environ.get("PYTHONPATH", "").split(os.pathsep)
         if "pip-build-env-" in entry), None)
    isolated_by_pip = build_env is not None
    parent, argv = _parent_python()
    candidates = [parent] if parent else []  # the Python running pip (the build frontend)
    if os.environ.get("VIRTUAL_ENV"):
        candidates.append(os.path.join(os.environ["VIRTUAL_ENV"], "bin", "python"))
    if "pip-build-env-" in os.environ.get("PYTHONPATH", ""):
        candidates.append(sys.executable)  # pip's older isolation: this Python, its site-packages hidden
    for python in candidates:
        found = _torch_of(python)
        if found is None:
            continue
        version, prefix = found
        frontend = "pip is building torchvor" if isolated_by_pip or "pip" in " ".join(argv or []) \
            else "torchvor is being built"
        return (
            f"{frontend} in an isolated environment ({build_env or sys.prefix}), which hides the torch {version} "
            f"installed in {prefix}.\n"
            "torchvor._C must be compiled against the torch it will run with. Build against that one with:\n"
            f"    {_pip_command(argv)}")
    where = f"in {sys.prefix}"
    if isolated_by_pip:
        where = (f"in pip's isolated build environment ({build_env}), nor for the Python that runs pip "
                 f"({parent or 'not found'})")
    return (
        f"no torch is installed {where}, and torchvor._C must be compiled against the torch it will run with.\n"
        "Install torch first (pinned: an unpinned torch pulls the newest CUDA build, several GB), "
        "then build without isolation:\n"
        f"    pip install {TORCH_PIN}\n"
        f"    {_pip_command(argv)}\n"
        "(or, in a clone of the repository, `bash scripts/setup.sh`, which makes .venv and does both).")


try:
    import torch
    from torch.utils import cpp_extension
except ImportError:
    sys.exit("torchvor: " + _no_torch_message())

from setuptools import find_packages, setup  # noqa: E402  (after the torch check, which needs only the stdlib)


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
    # -fno-math-errno: sqrt on a pack of lanes vectorises (core/host_packs.h); -Wno-psabi: those
    # packs are 32-byte vectors, always inlined, never passed across a call.
    cxx = ["-O3", "-std=c++17", "-fopenmp", "-fno-math-errno", "-Wno-psabi", "-g0"]
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
