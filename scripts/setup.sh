#!/usr/bin/env bash
# Sets up a virtual environment in .venv with torch 2.13 (CPU), builds torchvor
# in place and installs the test dependencies. Idempotent and quick when
# nothing changed: packages already present are not reinstalled, and the
# extension is rebuilt only when its sources, the build files, the torch it was
# built against or the build switches changed (a stamp in .venv records them).
# Never replaces an installed torch. Later scripts use .venv/bin/python.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null
fi
VENV_PY=.venv/bin/python
if ! "$VENV_PY" -c "import torch" 2>/dev/null; then
  # Pinned: an unpinned torch pulls the newest CUDA build (several GB).
  "$VENV_PY" -m pip install -q torch==2.13.0
fi

# Test and build dependencies (torch_geometric: pure Python, for torchvor.pyg's tests),
# installed only when one is missing (or setuptools is older than 77, the first to
# read pyproject's SPDX license).
if ! "$VENV_PY" - 2>/dev/null <<'PY'
import importlib.metadata
import numpy, scipy, pytest, wheel, ninja  # noqa: F401
assert int(importlib.metadata.version("setuptools").split(".")[0]) >= 77
assert importlib.metadata.version("torch_geometric") == "2.8.0.post1"  # torchvor.pyg's tests (pure Python)
PY
then
  "$VENV_PY" -m pip install -q numpy scipy pytest "setuptools>=77" wheel ninja torch_geometric==2.8.0.post1
fi

# What the built extension depends on (sources, build files, torch and Python
# versions, build switches, nvcc) and the extension itself ("path size mtime"),
# or a line saying why there is none to reuse. Reads no torch: it takes well under a second.
STAMP=.venv/torchvor-build.stamp
build_state() {
  "$VENV_PY" - <<'PY'
import hashlib, importlib.metadata, importlib.util, os, shutil, sys, sysconfig
digest = hashlib.sha256()
files = ["setup.py", "pyproject.toml"]
for folder, _, names in os.walk("csrc"):
    files += [os.path.join(folder, name) for name in names]
for path in sorted(files):
    digest.update(path.encode() + b"\0")
    with open(path, "rb") as handle:
        digest.update(handle.read() + b"\0")
suffix = sysconfig.get_config_var("EXT_SUFFIX")
print(f"sources {digest.hexdigest()}")
print(f"torch {importlib.metadata.version('torch')} python {sys.version.split()[0]} {suffix}")
print("switches", *(f"{name}={os.environ.get(name, '')}" for name in
                    ("TORCHVOR_FORCE_CPU", "TORCHVOR_FORCE_CUDA", "TORCH_CUDA_ARCH_LIST", "CUDA_HOME", "CXX", "CC")),
      "nvcc", shutil.which("nvcc") or "-")
sys.path = [entry for entry in sys.path if entry not in ("", os.getcwd())]  # the install, not ./torchvor
spec = importlib.util.find_spec("torchvor")  # a top-level find_spec does not import the package
extension = os.path.join("torchvor", "_C" + suffix)
if spec is None or os.path.realpath(os.path.dirname(spec.origin)) != os.path.realpath("torchvor"):
    print("torchvor is not installed in place from this tree")
elif not os.path.isfile(extension):
    print("torchvor._C is not built")
else:
    status = os.stat(extension)
    print(f"extension {extension} {status.st_size} {status.st_mtime_ns}")
PY
}
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$(build_state)" ]; then
  echo "torchvor: the built extension is up to date (same sources, torch and build switches)"
else
  rm -f "$STAMP"
  "$VENV_PY" -m pip install -q --no-build-isolation --no-deps -e .
  build_state >"$STAMP"
fi
"$VENV_PY" -c "import torch, torchvor; print('torchvor', torchvor.__version__, 'on torch', torch.__version__, '| threads:', torch.get_num_threads())"
