#!/usr/bin/env bash
# Sets up a virtual environment in .venv with torch 2.13 (CPU), builds torchvor
# in place and installs the test dependencies. Idempotent; never replaces an
# installed torch. Source it or run it: later scripts use .venv/bin/python.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
VENV_PY=.venv/bin/python
"$VENV_PY" -m pip install -q --upgrade pip >/dev/null
if ! "$VENV_PY" -c "import torch" 2>/dev/null; then
  # Pinned: an unpinned torch pulls the newest CUDA build (several GB).
  "$VENV_PY" -m pip install -q torch==2.13.0
fi
"$VENV_PY" -m pip install -q numpy scipy pytest setuptools wheel ninja
"$VENV_PY" -m pip install -q --no-build-isolation --no-deps -e .
"$VENV_PY" -c "import torch, torchvor; print('torchvor', torchvor.__version__, 'on torch', torch.__version__, '| threads:', torch.get_num_threads())"
