#!/usr/bin/env bash
# One call on the GPU machine: build for sm_90, then run the steps named (default: cudatests):
# the tests (CPU and CUDA), the benchmarks, profiles and sanitizers; logs go to $OUT.
#   usage: bash benchmarks/gpu_check.sh [tests|cudatests|bench|graph|periodic|power|distributed|compare|time|fuzz|lloyd10m|profile|timeline|sanitize|ncu|build]...
# compare needs BASELINE=<source tree of another commit> (e.g. `git archive <commit> | tar -x -C .baseline`):
# it is built beside this tree, its CUDA outputs compared bit for bit, and both timed in turns.
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
if [ -n "${BASELINE:-}" ]; then  # built in the background, beside this tree's build
  BASELINE=$(cd "$BASELINE" && pwd)  # absolute: the runs import it from /tmp
  (cd "$BASELINE" && python3 setup.py build_ext --inplace >"$OUT/baseline_build.log" 2>&1; echo $? >"$OUT/baseline_build.rc") &
fi
# ALSO_TIME: more source trees (space-separated) that compare and time time in turns
# with this one, built the same way (their build logs: $OUT/also_<name>_build.log).
also_time=()
for tree in ${ALSO_TIME:-}; do
  tree=$(cd "$tree" && pwd); also_time+=("$tree")
  (cd "$tree" && python3 setup.py build_ext --inplace >"$OUT/also_$(basename "$tree")_build.log" 2>&1) &
done
# Verbose, each line stamped with the second it arrived: ninja prints a
# compile's command when it finishes, so compile_times.txt lists when each
# object was done.
if [ -z "${SKIP_BUILD:-}" ]; then  # SKIP_BUILD=1: the build already there (steps run side by side)
python3 -m pip install -v --no-build-isolation --no-deps --no-index -e . 2>&1 \
  | while IFS= read -r line; do printf '%(%s)T %s\n' -1 "$line"; done >"$OUT/build.log"
[ "${PIPESTATUS[0]}" = 0 ] || { tail -60 "$OUT/build.log"; exit 1; }
echo "build: $(( $(date +%s) - start )) s"
grep -E '^[0-9]+ +\[[0-9]+/[0-9]+\]' "$OUT/build.log" \
  | sed -E "s/^([0-9]+) +(\[[0-9]+\/[0-9]+\]).* -c ([^ ]+).*/\1 \2 \3/" \
  | awk -v start="$start" '{printf "%4d s  %s %s\n", $1 - start, $2, $3}' | tee "$OUT/compile_times.txt"
fi
# Times voronoi at the default k on 10M blue, perturbed and white points, two rounds,
# the builds given in turns, each dtype of COMPARE_DTYPES (default float32).
time_builds() {
  (cd /tmp && PYTHONPATH="$REPO" python3 - <<'PY'
import torch, torchvor.samples as s
torch.save(s.blue_noise(10_000_000, iters=30, device="cuda").cpu(), "/tmp/blue_10m.pt")
torch.save(s.perturbed_grid(10_000_000), "/tmp/perturbed_10m.pt")
torch.save(s.white_noise(10_000_000), "/tmp/white_10m.pt")
PY
  for round in 1 2; do
    for build in "$@"; do
      echo "round $round: $build"
      for dtype in ${COMPARE_DTYPES:-float32}; do
        PYTHONPATH="$build" python3 "$REPO/scripts/compare_builds.py" time /tmp/blue_10m.pt /tmp/perturbed_10m.pt \
          /tmp/white_10m.pt --device cuda --dtype $dtype
      done
    done
  done)
}
status=0
for step in "${@:-cudatests}"; do
  case "$step" in
    tests) python3 -m pytest -q -p no:cacheprovider tests 2>&1 | tee "$OUT/tests.log" | tail -15 || status=1 ;;
    cudatests)  # CUDA_TESTS_K narrows them (a pytest -k expression, and-ed with "cuda"); CUDA_TEST_SHARDS
                # pytests (default one a GPU visible), each an interleaved share of the tests (tests/conftest.py's
                # --shard), spread over the GPUs
      gpus=$(nvidia-smi --query-gpu=index --format=csv,noheader | wc -l)
      [ -z "${CUDA_VISIBLE_DEVICES:-}" ] || gpus=$(echo "$CUDA_VISIBLE_DEVICES" | tr ',' '\n' | wc -l)
      visible=(${CUDA_VISIBLE_DEVICES:+${CUDA_VISIBLE_DEVICES//,/ }}); [ ${#visible[@]} -gt 0 ] || visible=($(seq 0 $((gpus - 1))))
      shards=${CUDA_TEST_SHARDS:-$gpus}
      for shard in $(seq 0 $((shards - 1))); do
        CUDA_VISIBLE_DEVICES=${visible[$((shard % gpus))]} python3 -m pytest -q -p no:cacheprovider --shard $shard/$shards \
          -k "cuda${CUDA_TESTS_K:+ and ($CUDA_TESTS_K)}" tests > "$OUT/cudatests.$shard.log" 2>&1 &
      done
      wait
      cat "$OUT"/cudatests.*.log > "$OUT/cudatests.log"; rm -f "$OUT"/cudatests.*.log
      grep -E "passed|failed|Error|assert" "$OUT/cudatests.log" | tail -30
      ! grep -qE "[0-9]+ (failed|error)" "$OUT/cudatests.log" || status=1 ;;
    bench)
      python3 benchmarks/bench_knn.py --device cuda --sizes 1M --k 35 --points jittered --methods torchvor,ckdtree 2>&1 | tee "$OUT/bench_knn.log"
      python3 benchmarks/bench_knn.py --device cuda --sizes 10M --k 190 --points uniform --methods torchvor 2>&1 | tee -a "$OUT/bench_knn.log"
      python3 benchmarks/bench_voronoi.py --device cuda --sizes 100K,1M,10M --lloyd-iteration 2>&1 | tee "$OUT/bench_voronoi.log"
      python3 benchmarks/bench_voronoi.py --device cuda --sizes 100M --kinds blue 2>&1 | tee -a "$OUT/bench_voronoi.log"
      python3 benchmarks/bench_lloyd.py --device cuda 2>&1 | tee "$OUT/bench_lloyd.log"
      python3 benchmarks/bench_graph.py --device cuda --sizes 1M,10M 2>&1 | tee "$OUT/bench_graph.log" ;;
    periodic)  # voronoi and knn with periodic=True against plain (1M, 10M blue and white, float32 and float64)
      for dtype in float32 float64; do
        python3 benchmarks/bench_periodic.py --device cuda --sizes 1M,10M --repeats 3 --dtype $dtype $( [ $dtype = float32 ] && echo --profile) 2>&1 | tee -a "$OUT/bench_periodic.log"
      done ;;
    power)  # power_weights to 1e-6, then the power diagram against plain voronoi (POWER_SIZES, default 1M,10M,
            # blue and white; POWER_ARGS more options, e.g. --profile); with BASELINE, the baseline's too, once it is built
            # (at BASELINE_POWER_SIZES, default POWER_SIZES)
      python3 benchmarks/bench_power.py --device cuda --sizes ${POWER_SIZES:-1M,10M} --repeats 3 ${POWER_ARGS:-} 2>&1 | tee "$OUT/bench_power.log"
      if [ -n "${BASELINE:-}" ]; then
        wait
        (cd /tmp && PYTHONPATH="$BASELINE" python3 "$REPO/benchmarks/bench_power.py" --device cuda \
          --sizes ${BASELINE_POWER_SIZES:-${POWER_SIZES:-1M,10M}} --repeats 3) 2>&1 | tee "$OUT/bench_power_baseline.log"
      fi ;;
    graph)  # voronoi_graph and the cells' backward against voronoi (GRAPH_SIZES, default 1M,10M, blue and white);
            # with BASELINE, the baseline's too, once it is built
      python3 benchmarks/bench_graph.py --device cuda --sizes ${GRAPH_SIZES:-1M,10M} --repeats 3 --profile 2>&1 | tee "$OUT/bench_graph.log"
      if [ -n "${BASELINE:-}" ]; then
        wait
        (cd /tmp && PYTHONPATH="$BASELINE" python3 "$REPO/benchmarks/bench_graph.py" --device cuda \
          --sizes ${GRAPH_SIZES:-1M,10M} --repeats 3) 2>&1 | tee "$OUT/bench_graph_baseline.log"
      fi ;;
    compare)
      wait
      [ "$(cat "$OUT/baseline_build.rc" 2>/dev/null)" = 0 ] || { echo "baseline build failed"; tail -30 "$OUT/baseline_build.log"; status=1; continue; }
      (cd /tmp && PYTHONPATH="$REPO" python3 "$REPO/scripts/compare_builds.py" run /tmp/new.pt --device cuda \
        && PYTHONPATH="$BASELINE" python3 "$REPO/scripts/compare_builds.py" run /tmp/old.pt --device cuda \
        && python3 "$REPO/scripts/compare_builds.py" compare /tmp/old.pt /tmp/new.pt) 2>&1 | tee "$OUT/compare.log" || status=1
      time_builds "$REPO" "$BASELINE" "${also_time[@]}" 2>&1 | tee "$OUT/compare_time.log" ;;
    time) wait; time_builds "$REPO" "${also_time[@]}" 2>&1 | tee "$OUT/time.log" ;;  # this build (and ALSO_TIME's), as compare times it
    fuzz)  # the fuzzing campaign on CUDA, thread and warp cells: FUZZ_CASES cases from FUZZ_START (FUZZ_SEED,
           # FUZZ_MAX_N) in FUZZ_WORKERS processes (over the GPUs there are), each starting none after FUZZ_SECONDS (0: no budget)
           # and stopped FUZZ_GRACE seconds later;
           # a line a case in fuzz_cases.log
      python3 tests/fuzz.py --device cuda --cells all --cases ${FUZZ_CASES:-10000} --start ${FUZZ_START:-0} \
        --seed ${FUZZ_SEED:-1} --max-n ${FUZZ_MAX_N:-1000000} --sample ${FUZZ_SAMPLE:-4} --workers ${FUZZ_WORKERS:-12} --grace ${FUZZ_GRACE:-60} \
        --compare-max-n ${FUZZ_COMPARE_MAX_N:-5000} --time-budget ${FUZZ_SECONDS:-0} --json "$OUT/fuzz.json" \
        > "$OUT/fuzz.log" 2>&1; grep -A40 "^fuzz summary" "$OUT/fuzz.log" | grep -v "^  \[second_moment\]\|^      replay" | head -60
      cat "$OUT"/fuzz.json.worker*.log > "$OUT/fuzz_cases.log" 2>/dev/null; rm -f "$OUT"/fuzz.json.worker* "$OUT"/fuzz.json.next  # few files come back
      grep -q "^fuzz: OK" "$OUT/fuzz.log" || status=1 ;;
    distributed)  # torchvor.distributed over the GPUs there are (NCCL, a GPU a rank): the fuzzer's cases against
                  # the single-process calls (DIST_FUZZ_CASES), then strong and weak scaling (DIST_SIZES) of blue noise
                  # (DIST_BLUE_ITERS Lloyd iterations, default 30; each rank makes the cloud on its GPU)
      gpus=$(nvidia-smi --query-gpu=index --format=csv,noheader | wc -l)
      python3 tests/fuzz_distributed.py --device cuda --size $gpus --seed ${FUZZ_SEED:-1} --cases ${DIST_FUZZ_CASES:-60} \
        --max-n 20000 --quiet 2>&1 | grep -v Warning | tail -20 | tee "$OUT/distributed.log"
      grep -q "ranks: OK" "$OUT/distributed.log" || status=1
      python3 benchmarks/bench_distributed.py --device cuda --sizes ${DIST_SIZES:-10M,100M} --ranks 1,$gpus \
        --blue-iters ${DIST_BLUE_ITERS:-30} 2>&1 | grep -v USDT | tee -a "$OUT/distributed.log"
      python3 benchmarks/bench_distributed.py --device cuda --sizes ${DIST_WEAK_SIZES:-100M} --ranks 1,$gpus --weak \
        --blue-iters ${DIST_BLUE_ITERS:-30} --phases 2>&1 \
        | grep -v USDT | tee -a "$OUT/distributed.log" ;;
    lloyd10m) python3 benchmarks/bench_lloyd.py --device cuda --sizes 10M --iters 20 2>&1 | grep -v USDT | tee "$OUT/bench_lloyd10m.log" ;;
    timeline)  # where a voronoi call's and a Lloyd step's time goes, GPU activity by activity (blue noise,
               # the op's default k; TIMELINE_SIZES)
      python3 benchmarks/profile_gpu.py --device cuda --sizes ${TIMELINE_SIZES:-1M,10M} --timeline --rows 8 2>&1 \
        | grep -v -e USDT -e profiler -e _warn_once | tee "$OUT/timeline.log" ;;
    profile) python3 benchmarks/profile_gpu.py --device cuda --sizes 1M --knn-10m 2>&1 | grep -v USDT | tee "$OUT/profile.log" ;;
    ncu)  # the first launch of a clip kernel under Nsight Compute, on a 1M jittered grid: NCU_CALL (voronoi, default, at
          # k=35; or voronoi_graph at the op's k), NCU_KERNEL (a regex of the demangled name, default ClipFunctor;
          # e.g. 'ClipFunctor<double, double, .int.32, .bool.0, .bool.0, .bool.1' for the graph's tier-32 face kernel:
          # ncu's demangled names spell template arguments as (int)32 and (bool)1), NCU_ARGS
          # more options (e.g. "--section SourceCounters": the stalls' source lines)
      python3 - >"$OUT/ncu_prep.log" 2>&1 <<'PY'
import torch, torchvor.samples
torch.save(torchvor.samples.jittered_grid(1_000_000, seed=1), "/tmp/jittered_1m.pt")
PY
      call=${NCU_CALL:-voronoi}
      ncu --clock-control none --kernel-name-base demangled -k "regex:${NCU_KERNEL:-ClipFunctor}" --launch-count 1 --section SpeedOfLight --section WarpStateStats \
          --section Occupancy --section LaunchStats --section MemoryWorkloadAnalysis --section SchedulerStats ${NCU_ARGS:-} \
          python3 -c "
import torch, torchvor
p = torch.load('/tmp/jittered_1m.pt').cuda()
kwargs = {'k': 35} if '$call' == 'voronoi' else {}
getattr(torchvor, '$call')(p, ([0,0,0],[1,1,1]), on_failure='flag', **kwargs); torch.cuda.synchronize()
" 2>&1 | grep -v '^==PROF==' | tee "$OUT/ncu.log" | grep -E "Duration|Throughput|Registers|Achieved Occupancy|Theoretical Occupancy|Stall|Warp Cycles|Local|L1/TEX Hit|L2 Hit|Eligible|Issued|Block Limit|Dynamic|Static|Executed Ipc" ;;
    sanitize)  # under each of SANITIZE_TOOLS (default memcheck racecheck synccheck):
               # white noise (SANITIZE_N points; SANITIZE_N=0: none) under each SANITIZE_SETTINGS: space-separated environment settings, each a run ("default" = none),
               # e.g. "default TORCHVOR_CELLS=cooperative,TORCHVOR_CELL_START=box"
      tools=${SANITIZE_TOOLS:-memcheck racecheck synccheck}
      for setting in $( [ "${SANITIZE_N:-1}" = 0 ] || echo ${SANITIZE_SETTINGS:-default}); do
        for tool in $tools; do
          echo "$tool: $setting" | tee -a "$OUT/sanitize.log"
          env $( [ "$setting" = default ] || echo "${setting//,/ }" ) \
            compute-sanitizer --tool $tool --error-exitcode 9 python3 -c "
import torch, torchvor, torchvor.samples
p = torchvor.samples.white_noise(${SANITIZE_N:-100000}, device='cuda')
torchvor.knn(p, 35); c = torchvor.voronoi(p, ([0,0,0],[1,1,1]), k=32, on_failure='flag')
r = torchvor.lloyd(p, ([0,0,0],[1,1,1]), iters=2)  # two lloyd_step ops
g = torchvor.voronoi_graph(p, ([0,0,0],[1,1,1]), on_failure='flag')  # the faces' kernels
q = p.clone().requires_grad_(); torchvor.voronoi(q, ([0,0,0],[1,1,1])).volume.sum().backward()
torch.cuda.synchronize(); print('$tool run ok, volume sum', c.volume.sum().item(), 'lloyd', r.sum().item(),
      'edges', g.edge_index.shape[1], 'grad', q.grad.abs().sum().item())
" > "$OUT/sanitize_run.log" 2>&1; code=$?
          tail -5 "$OUT/sanitize_run.log" | tee -a "$OUT/sanitize.log"; [ $code = 0 ] || status=1
          grep -m 12 -A 6 -E "^========= +(Error|Warning)" "$OUT/sanitize_run.log" >> "$OUT/sanitize_raw.log"
        done
      done
      # and a slice of the fuzzing campaign (SANITIZE_FUZZ_CASES cases of up to SANITIZE_FUZZ_MAX_N
      # points, thread and warp cells, seed SANITIZE_FUZZ_SEED) under each tool
      for tool in $tools; do
        echo "$tool: fuzz slice" | tee -a "$OUT/sanitize.log"
        compute-sanitizer --tool $tool --error-exitcode 9 python3 tests/fuzz.py --device cuda --cells all \
          --cases ${SANITIZE_FUZZ_CASES:-30} --seed ${SANITIZE_FUZZ_SEED:-1} --max-n ${SANITIZE_FUZZ_MAX_N:-3000} \
          --sample 1 --suspects 0 --quiet > "$OUT/sanitize_run.log" 2>&1; code=$?
        # each hazard's kind and where (kernel, line), counted, and the summary
        grep -E "^========= +(Error|Warning|Race reported|Saved host backtrace| +at )|SUMMARY" "$OUT/sanitize_run.log" \
          | sed -E 's/0x[0-9a-f]+/0x./g' | sort | uniq -c | sort -rn | head -40 | tee -a "$OUT/sanitize.log"
        # the first hazards in full (kernel, source line, both accesses), for attribution
        grep -m 12 -A 6 -E "^========= +(Error|Warning)" "$OUT/sanitize_run.log" >> "$OUT/sanitize_raw.log"
        [ $code = 0 ] || status=1
      done
      rm -f "$OUT/sanitize_run.log" ;;
    build) ;;  # the build alone
    *) echo "gpu_check.sh: unknown step '$step'" >&2; status=1 ;;
  esac
done
exit $status
