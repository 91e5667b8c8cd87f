#!/usr/bin/env bash
# Compile the CUDA sources for sm_90 on a machine without a CUDA build of
# torch (the development machine: nvcc, and torch's CPU wheel, which ships
# the ATen/c10 CUDA headers but not the CUDA libraries' headers they
# include). Catches compile errors and shows each kernel's registers and
# stack frame (ptxas) before any device time is spent. Nothing is linked or
# installed: the CUDA libraries' headers are replaced by stubs that declare
# only the handle and status types torch's headers name.
#   usage: bash scripts/nvcc_check.sh [csrc/cuda/voronoi.cu ...]   (default: every .cu)
#   output: one line per kernel, "registers  stack-bytes  kernel", and the full ptxas log
#   in $TMPDIR/nvcc_check/<source>.log
set -eu -o pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
cd "$REPO"
WORK=${TMPDIR:-/tmp}/nvcc_check
STUBS=$WORK/stubs
mkdir -p "$STUBS/c10/cuda/impl"
echo '#pragma once' >"$STUBS/c10/cuda/impl/cuda_cmake_macros.h"
printf 'typedef struct cublasContext* cublasHandle_t;\ntypedef int cublasStatus_t;\n' >"$STUBS/cublas_v2.h"
printf 'typedef struct cublasLtContext* cublasLtHandle_t;\n' >"$STUBS/cublasLt.h"
printf 'typedef struct cusparseContext* cusparseHandle_t;\ntypedef int cusparseStatus_t;\n' >"$STUBS/cusparse.h"
printf 'typedef struct cusolverDnContext* cusolverDnHandle_t;\n' >"$STUBS/cusolverDn.h"
printf 'typedef int cusolverStatus_t;\n' >"$STUBS/cusolver_common.h"
TORCH_INCLUDE=$(python -c "import os, torch; print(os.path.join(os.path.dirname(torch.__file__), 'include'))")
PYTHON_INCLUDE=$(python -c "import sysconfig; print(sysconfig.get_paths()['include'])")
# The flags of setup.py's CUDA build, for sm_90 only.
FLAGS=(-O3 -std=c++17 -lineinfo --expt-relaxed-constexpr -arch=sm_90 -Xptxas -v)
INCLUDES=(-I"$STUBS" -I"$TORCH_INCLUDE" -I"$TORCH_INCLUDE/torch/csrc/api/include" -I"$PYTHON_INCLUDE" -Icsrc)
sources=("$@")
[ ${#sources[@]} -gt 0 ] || sources=(csrc/cuda/*.cu)
status=0
for source in "${sources[@]}"; do
  log=$WORK/$(basename "$source").log
  if nvcc "${FLAGS[@]}" "${INCLUDES[@]}" -c "$source" -o "$WORK/$(basename "$source").o" >"$log" 2>&1; then
    echo "## $source: compiled"
  else
    echo "## $source: FAILED (full log: $log)"
    grep -E "error" "$log" | head -20
    status=1
    continue
  fi
  # ptxas prints "Compiling entry function '<mangled>'", then the frame, then the registers.
  awk '/Compiling entry function/ { name = $0; sub(/.*function \047/, "", name); sub(/\047.*/, "", name) }
       /bytes stack frame/ { stack = $1 }
       /Used [0-9]+ registers/ { for (i = 1; i <= NF; ++i) if ($i == "Used") regs = $(i + 1); print regs, stack, name }' "$log" |
    sort -u -k3 | while read -r regs stack name; do
      printf '%4s regs %6s B stack  %s\n' "$regs" "$stack" "$(echo "$name" | c++filt | cut -c1-160)"
    done
done
exit $status
