#!/usr/bin/env bash
# One call on the GPU machine: build for sm_90, run the tests (CPU and CUDA),
# the CUDA smoke check and the benchmarks; logs go to $OUT.
#   usage: bash benchmarks/gpu_check.sh [smoke|tests|cudatests|ab|lanes|crossk|kinds|bluek|density|residency|bench|hard|lloyd10m|breakdown|build|sweep|timeline|profile|sanitize|ncu|ncusource|envab|ncuknn]...
set -u -o pipefail
OUT=${OUT:-/tmp/torchvor_gpu}
mkdir -p "$OUT"
REPO=$(cd "$(dirname "$0")/.." && pwd)
cd "$REPO"
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TORCHVOR_FORCE_CUDA=1
# The image's default CXX (/opt/gcc/bin/g++) links libstdc++ statically into
# the extension, and then every error message that formats a number segfaults.
export CXX=/usr/bin/g++ CC=/usr/bin/gcc
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
echo "commit ${COMMIT:-$(git rev-parse --short HEAD 2>/dev/null || echo unknown)}" | tee -a "$OUT/gpu.txt"
start=$(date +%s)
# Verbose, each line stamped with the second it arrived: ninja prints a
# compile's command when it finishes, so compile_times.txt lists when each
# object was done.
python3 -m pip install -v --no-build-isolation --no-deps --no-index -e . 2>&1 \
  | while IFS= read -r line; do printf '%(%s)T %s\n' -1 "$line"; done >"$OUT/build.log"
[ "${PIPESTATUS[0]}" = 0 ] || { tail -60 "$OUT/build.log"; exit 1; }
echo "build: $(( $(date +%s) - start )) s"
grep -E '^[0-9]+ +\[[0-9]+/[0-9]+\]' "$OUT/build.log" \
  | sed -E "s/^([0-9]+) +(\[[0-9]+\/[0-9]+\]).* -c ([^ ]+).*/\1 \2 \3/" \
  | awk -v start="$start" '{printf "%4d s  %s %s\n", $1 - start, $2, $3}' | tee "$OUT/compile_times.txt"
status=0
for step in "${@:-smoke}"; do
  case "$step" in
    smoke) python3 benchmarks/gpu_smoke.py --sizes 100000,1000000,10000000 2>&1 | tee "$OUT/smoke.log" || status=1 ;;
    tests) python3 -m pytest -q -p no:cacheprovider tests 2>&1 | tee "$OUT/tests.log" | tail -15 || status=1 ;;
    cudatests)  # CUDA_TESTS_K narrows them (a pytest -k expression, and-ed with "cuda")
      python3 -m pytest -q -p no:cacheprovider -k "cuda${CUDA_TESTS_K:+ and ($CUDA_TESTS_K)}" tests 2>&1 \
        | tee "$OUT/cudatests.log" | grep -E "passed|failed|Error|assert" | tail -30 || status=1 ;;
    ab|lanes)  # one build under several settings: ROUNDS rounds of ab_time.py under each environment
               # setting of AB ("default" = no variable); lanes first prints the thread/warp crossover tables
      if [ "$step" = lanes ]; then
        python3 benchmarks/crossover.py 2>&1 | grep --line-buffered -v -e USDT -e profiler -e _warn_once | tee "$OUT/crossover.log"
      fi
      for round in $(seq ${ROUNDS:-2}); do
        for setting in ${AB:-default TORCHVOR_KNN=thread}; do
          if [ "$setting" = default ]; then assign=(); else assign=("$setting"); fi
          env "${assign[@]}" python3 benchmarks/ab_time.py "$setting" 2>&1 \
            | grep --line-buffered -v -e USDT -e profiler -e _warn_once | tee -a "$OUT/$step.log"
        done
      done ;;
    crossk)  # whole voronoi calls at 1M, thread against warp cells, per kind and first-pass k
      python3 benchmarks/crossover.py --op k 2>&1 | grep -v -e USDT -e profiler -e _warn_once | tee "$OUT/crossk.log" ;;
    kinds)  # thread against warp cells on many kinds of point set, beside the pilot's neighbour statistics
      python3 benchmarks/crossover.py --op kinds --sizes ${KINDS_SIZES:-1M,10M} 2>&1 \
        | grep --line-buffered -v -e USDT -e profiler -e _warn_once | tee "$OUT/kinds.log" ;;
    bluek)  # blue noise against first-pass k (0 = the op's pilot)
      python3 benchmarks/bench_voronoi.py --device cuda --kinds blue --sizes ${BLUEK_SIZES:-1M,10M} \
        --k ${BLUEK_K:-0,16,18,20,24} 2>&1 | grep -v USDT | tee "$OUT/bluek.log" ;;
    density)  # kNN and voronoi against the grid's points per cell (TORCHVOR_POINTS_PER_CELL_SCALE)
      python3 benchmarks/sweep_points_per_cell.py --device cuda --sizes ${DENSITY_SIZES:-1M,10M} 2>&1 \
        | grep -v -e USDT -e profiler -e _warn_once | tee "$OUT/density.log" ;;
    residency)  # clip kernel against resident blocks per SM of one-thread-per-cell clipping
      python3 benchmarks/sweep_cell_residency.py --device cuda --sizes ${RESIDENCY_SIZES:-1M,10M} 2>&1 \
        | grep -v -e USDT -e profiler -e _warn_once | tee "$OUT/residency.log" ;;
    bench)
      python3 benchmarks/bench_knn.py --device cuda --sizes 1M --k 35 --points jittered --methods torchvor,ckdtree 2>&1 | tee "$OUT/bench_knn.log"
      python3 benchmarks/bench_knn.py --device cuda --sizes 10M --k 190 --points uniform --methods torchvor 2>&1 | tee -a "$OUT/bench_knn.log"
      python3 benchmarks/bench_voronoi.py --device cuda --sizes 100K,1M,10M --lloyd-iteration 2>&1 | tee "$OUT/bench_voronoi.log"
      python3 benchmarks/bench_voronoi.py --device cuda --sizes 100M --kinds blue 2>&1 | tee -a "$OUT/bench_voronoi.log"
      python3 benchmarks/bench_lloyd.py --device cuda 2>&1 | tee "$OUT/bench_lloyd.log" ;;
    hard)  # inputs whose cells reach into empty space (clusters with voids, a box 3x wide); HARD_K: settings
           # of TORCHVOR_VERTEX_BALLS_K (10^9 alone: the radius of security, the behaviour before)
      python3 benchmarks/bench_hard_inputs.py --device cuda --sizes ${HARD_SIZES:-100K,1M} \
        --vertex-balls-k ${HARD_K:-default} 2>&1 | grep -v -e USDT -e profiler -e _warn_once | tee "$OUT/hard.log" ;;
    lloyd10m) python3 benchmarks/bench_lloyd.py --device cuda --sizes 10M --iters 20 2>&1 | grep -v USDT | tee "$OUT/bench_lloyd10m.log" ;;
    ncusource)  # source-level profile of the clip kernels: a warp per cell on white noise (k=64) and on a
                # perturbed grid (k=48), a thread per cell on blue noise (k=24); NCU_CASES picks some
                # (default all); summaries and SASS CSVs in $OUT
      python3 - >"$OUT/ncu_prep.log" 2>&1 <<'PY'
import sys, torch, torchvor.samples
sys.path.insert(0, "benchmarks")
import common
torch.save(torchvor.samples.white_noise(1_000_000, seed=1), "/tmp/white_1m.pt")
torch.save(torchvor.samples.perturbed_grid(1_000_000, seed=1), "/tmp/perturbed_1m.pt")
blue, _ = common.make_points("blue", 1_000_000, seed=0, dtype=torch.float32, device=torch.device("cuda"),
                             cache_dir=common.Path("benchmarks/.cache"))
torch.save(blue.cpu(), "/tmp/blue_1m.pt")
PY
      for case in "warp_white white 64 for_each_cooperative_claimed_kernel" "warp_perturbed perturbed 48 for_each_cooperative_claimed_kernel" \
                  "thread_blue blue 24 for_each_claimed_kernel"; do
        read -r name points k kernel <<<"$case"
        [[ " ${NCU_CASES:-$name} " == *" $name "* ]] || continue
        ncu --clock-control none --set full --import-source yes --kernel-name-base demangled \
            -k "regex:${kernel}<.*ClipFunctor" --launch-count 1 -f -o "$OUT/clip_$name" python3 -c "
import torch, torchvor
p = torch.load('/tmp/${points}_1m.pt').cuda()
torchvor.voronoi(p, ([0,0,0],[1,1,1]), k=$k, on_failure='flag'); torch.cuda.synchronize()
" 2>&1 | grep -v '^==PROF==' | tail -3
        python3 benchmarks/ncu_source.py "$OUT/clip_$name.ncu-rep" --csv-dir "$OUT" 2>&1 | tee "$OUT/ncu_source_$name.log" | head -70
        ncu --import "$OUT/clip_$name.ncu-rep" --page details 2>&1 | grep -E "Duration|Registers|Achieved Occupancy|Theoretical Occupancy|Issued Warp|Eligible|L1/TEX Hit|L2 Hit|Executed Ipc A|Avg. Active Threads|Local" | tee -a "$OUT/ncu_source_$name.log"
        rm -f "$OUT/clip_$name.ncu-rep"  # the CSVs and summaries above hold what is needed
      done ;;
    envab)  # ab_env.py: ENVAB_SETTINGS (default: the default against the rings) with ENVAB_ARGS
      python3 benchmarks/ab_env.py ${ENVAB_SETTINGS:-default TORCHVOR_KNN=thread} ${ENVAB_ARGS:-} 2>&1 \
        | grep --line-buffered -v -e USDT -e profiler -e _warn_once | tee -a "$OUT/envab.log" ;;
    ncuknn)  # the kNN kernel of voronoi on 1M blue noise (k=24) under ncu, per environment setting of
             # NCUKNN_SETTINGS ("default" = none, else NAME=VALUE[,NAME=VALUE], e.g. TORCHVOR_KNN=thread)
      python3 - >"$OUT/ncu_prep.log" 2>&1 <<'PY'
import sys, torch
sys.path.insert(0, "benchmarks")
import common
blue, _ = common.make_points("blue", 1_000_000, seed=0, dtype=torch.float32, device=torch.device("cuda"),
                             cache_dir=common.Path("benchmarks/.cache"))
torch.save(blue.cpu(), "/tmp/blue_1m.pt")
PY
      for setting in ${NCUKNN_SETTINGS:-default}; do
        echo "$setting" | tee -a "$OUT/ncuknn.log"
        env $( [ "$setting" = default ] || echo "${setting//,/ }" ) ncu --clock-control none --kernel-name-base demangled -k regex:KnnFunctor --launch-count 1 \
          --section SpeedOfLight --section WarpStateStats --section Occupancy --section LaunchStats --section SchedulerStats \
          --section InstructionStats --section MemoryWorkloadAnalysis python3 -c "
import torch, torchvor
p = torch.load('/tmp/blue_1m.pt').cuda()
torchvor.voronoi(p, ([0,0,0],[1,1,1]), k=24, on_failure='flag'); torch.cuda.synchronize()
" 2>&1 | grep -v '^==PROF==' | grep -E "Duration|Registers|Achieved Occupancy|Theoretical Occupancy|Block Limit|Issued Warp|Eligible|Executed Ipc A|Avg. Active Threads|Executed Instructions|L1/TEX Hit|L2 Hit|Dynamic Shared|Stall" | tee -a "$OUT/ncuknn.log"
      done ;;
    breakdown)  # one Lloyd step's wall time in nested parts, unprofiled (BREAKDOWN_SIZES)
      python3 benchmarks/lloyd_breakdown.py --sizes ${BREAKDOWN_SIZES:-1M} 2>&1 \
        | grep -v -e USDT -e profiler -e _warn_once | tee "$OUT/breakdown.log" ;;
    sweep) python3 benchmarks/sweep_lloyd_k.py --device cuda --sizes 1M --repeats 20 --timeline 2>&1 | grep -v USDT | tee "$OUT/sweep.log" ;;
    timeline)  # where a voronoi call's and a Lloyd step's time goes, GPU activity by activity (blue noise,
               # the op's default k; TIMELINE_SIZES)
      python3 benchmarks/profile_gpu.py --device cuda --sizes ${TIMELINE_SIZES:-1M,10M} --timeline --rows 8 2>&1 \
        | grep -v -e USDT -e profiler -e _warn_once | tee "$OUT/timeline.log" ;;
    profile) python3 benchmarks/profile_gpu.py --device cuda --sizes 1M --knn-10m 2>&1 | grep -v USDT | tee "$OUT/profile.log" ;;
    ncu)
      python3 - >"$OUT/ncu_prep.log" 2>&1 <<'PY'
import torch, torchvor.samples
torch.save(torchvor.samples.jittered_grid(1_000_000, seed=1), "/tmp/jittered_1m.pt")
PY
      ncu --clock-control none --kernel-name-base demangled -k regex:ClipFunctor --launch-count 1 --section SpeedOfLight --section WarpStateStats \
          --section Occupancy --section LaunchStats --section MemoryWorkloadAnalysis --section SchedulerStats \
          python3 -c "
import torch, torchvor
p = torch.load('/tmp/jittered_1m.pt').cuda()
torchvor.voronoi(p, ([0,0,0],[1,1,1]), k=35, on_failure='flag'); torch.cuda.synchronize()
" 2>&1 | grep -v '^==PROF==' | tee "$OUT/ncu.log" | grep -E "Duration|Throughput|Registers|Achieved Occupancy|Theoretical Occupancy|Stall|Warp Cycles|Local|L1/TEX Hit|L2 Hit|Eligible|Issued|Block Limit|Dynamic|Static|Executed Ipc" ;;
    sanitize)  # SANITIZE_SETTINGS: space-separated environment settings, each a run ("default" = none),
               # e.g. "default TORCHVOR_CELLS=cooperative,TORCHVOR_CELL_LANES=8"
      for setting in ${SANITIZE_SETTINGS:-default}; do
        for tool in memcheck racecheck; do
          echo "$tool: $setting" | tee -a "$OUT/sanitize.log"
          env $( [ "$setting" = default ] || echo "${setting//,/ }" ) \
            compute-sanitizer --tool $tool --error-exitcode 9 python3 -c "
import torch, torchvor, torchvor.samples
p = torchvor.samples.white_noise(100000, device='cuda')
torchvor.knn(p, 35); c = torchvor.voronoi(p, ([0,0,0],[1,1,1]), k=32, on_failure='flag')
r = torchvor.lloyd(p, ([0,0,0],[1,1,1]), iters=2)  # lloyd_step: its first k (64) leaves cells to retry
torch.cuda.synchronize(); print('$tool run ok, volume sum', c.volume.sum().item(), 'lloyd', r.sum().item())
" 2>&1 | tail -5 | tee -a "$OUT/sanitize.log" || status=1
        done
      done ;;
    build) ;;  # the build alone
    *) echo "gpu_check.sh: unknown step '$step'" >&2; status=1 ;;
  esac
done
exit $status
