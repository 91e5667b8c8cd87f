#!/usr/bin/env bash
# A/B on the GPU machine: builds OLD_TREE (another revision's sources, e.g.
# `mkdir ab_old && git archive REV | tar -x -C ab_old`; git ignores ab_*/, so
# name it in the device tool's carry), the trees in MID_TREES (space-separated,
# optional: A/B/C...) and this tree side by side under /tmp, then runs
# benchmarks/ab_time.py on each in turn, ROUNDS times. No pip install: each
# build is imported through PYTHONPATH (the machine must not have torchvor
# installed in editable mode, whose import hook would win). AB_SCRIPT, if set,
# runs instead of ab_time.py (a script under this checkout and its arguments,
# e.g. "benchmarks/ab_env.py default --pilot --kernels --rounds 5"), after a
# line "== LABEL, round R".
#   usage: [MID_TREES="ab_mid"] [AB_SCRIPT=...] bash benchmarks/ab_compare.sh OLD_TREE [ROUNDS] [NEW_LABEL]
set -eu -o pipefail
ROUNDS=${2:-2}
REPO=$(cd "$(dirname "$0")/.." && pwd)
export CXX=/usr/bin/g++ CC=/usr/bin/gcc TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=8 TORCHVOR_FORCE_CUDA=1
labels=(old)
sources=("$(cd "$1" && pwd)")
for mid in ${MID_TREES:-}; do
  labels+=("$(basename "$mid")")
  sources+=("$(cd "$mid" && pwd)")
done
for i in "${!labels[@]}"; do
  rm -rf "/tmp/ab_${labels[$i]}" && mkdir -p "/tmp/ab_${labels[$i]}"
  cp -r "${sources[$i]}"/. "/tmp/ab_${labels[$i]}/"
done
rm -rf /tmp/ab_new && mkdir -p /tmp/ab_new
(cd "$REPO" && tar --exclude='./ab_*' --exclude=./.git --exclude='./build' -cf - .) | tar -xf - -C /tmp/ab_new
labels+=(new)
for tree in "${labels[@]}"; do
  (cd "/tmp/ab_$tree" && python3 setup.py build_ext --inplace >"/tmp/ab_$tree.log" 2>&1) &
done
wait
for tree in "${labels[@]}"; do
  ls /tmp/ab_$tree/torchvor/_C*.so >/dev/null 2>&1 || { tail -30 "/tmp/ab_$tree.log"; exit 1; }
done
for round in $(seq "$ROUNDS"); do
  for tree in "${labels[@]}"; do
    label=$tree
    [ "$tree" = new ] && label=${3:-new}
    if [ -n "${AB_SCRIPT:-}" ]; then
      echo "== $label, round $round"
      # shellcheck disable=SC2086  # the script and its arguments, split on purpose
      (cd "$REPO" && PYTHONPATH=/tmp/ab_$tree python3 $AB_SCRIPT)
    else
      PYTHONPATH=/tmp/ab_$tree python3 "$REPO/benchmarks/ab_time.py" "$label, round $round"
    fi
  done
done
