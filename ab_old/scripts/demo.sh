#!/usr/bin/env bash
# One command on a fresh machine: set everything up, then run the main job on
# the built-in default input (Lloyd relaxation of white noise, with a picture).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/python -m pip install -q matplotlib || echo "matplotlib not installed: no picture"
mkdir -p demo_output
exec .venv/bin/python -m torchvor lloyd --iters 20 --out demo_output/relaxed.npy --plot demo_output/lloyd.png "$@"
