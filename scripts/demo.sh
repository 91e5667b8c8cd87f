#!/usr/bin/env bash
# One command on a fresh machine: set everything up, then run the main job on
# the built-in default input (Lloyd relaxation of white noise, with a picture).
# Writes demo_output/relaxed.npy and, where matplotlib is available (it is
# installed here when missing, if the package index can be reached),
# demo_output/lloyd.png; without matplotlib the picture is skipped with a note.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if ! .venv/bin/python -c "import matplotlib" 2>/dev/null; then
  .venv/bin/python -m pip install -q matplotlib || echo "torchvor demo: matplotlib could not be installed: no picture"
fi
mkdir -p demo_output
exec .venv/bin/python -m torchvor lloyd --iters 20 --out demo_output/relaxed.npy --plot demo_output/lloyd.png "$@"
