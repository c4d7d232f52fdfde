#!/usr/bin/env bash
# The paper scale on a GPU machine that may be taken away at any time (docs/gpu.md). Without a package index there,
# run `bash scripts/gpu_wheels.sh` first where there is one and copy .whl/ along. Modes (MODE):
#   start   (first command)  installs the wheels, starts the whole work DETACHED (setsid: it outlives the command and
#           runs as long as the machine does), then watches it for WATCH_S seconds and packs what is finished into $OUT;
#   watch   (each later one) watches the detached work for WATCH_S seconds and packs again;
#   fg      (a machine that stays, or a CPU dry run)  the same work in the foreground, stopped at BUDGET_S, then packed;
#   pack    (tests)          packs RESULTS into OUT, as each command ends.
#   python scripts/gpu_local.py away                  # here, optional: results/ out of the checkout (a smaller copy)
#   MODE=start FAMILIES='HalfCheetahDir HalfCheetahVel' FILL=kuhn WATCH_S=555 bash scripts/gpu_paper_scale.sh
#   MODE=watch WATCH_S=<seconds you choose> bash scripts/gpu_paper_scale.sh          # as often as the machine lives
#   python scripts/gpu_local.py back                  # here, after the GPU work (also when it failed)
#   python scripts/gpu_local.py unpack <the copied-back $OUT folder> --logs <a new folder>
# What is copied to the machine stays small: `away` moves results/ out (the committed paper cells go along as a
# slim copy in .gpu/committed) and `unpack` keeps the checkpoints of unfinished runs in .gpu/resume, which the next
# machine's first command copies into its results and resumes from.
# The work: BENCH=1 first measures seed-steps/s at k = BENCH_SEEDS (default 3, chunks of 100 steps: a job's) (benchmarks/seed_throughput.py, pinned to core 0
# while the first family's data is collected on the other cores; the experiment waits for it: its compiles have
# taken over 9 minutes); then per family: collect its paper data over all cores (the next family's
# collection runs beside the current experiment, niced, on a quarter of the cores), and `bati experiment E
# --scale SCALE` for each E of EXPERIMENTS (default main) with METHODS x SEEDS, one job at a time (WORKERS; a job is one method's seeds vmapped in one
# program), its evaluation's MuJoCo envs stepped by EVAL_WORKERS processes. Measured on an H100 (docs/performance.md):
# three jobs side by side ran 4.3-5.6 ms per step each against 0.9 ms for one alone (the
# processes time-slice the GPU), while one evaluation of 3 seeds took 16 s on one core: so one job at a time, and
# evaluation over the spare cores.
# Each command's pack is $OUT/results.tar.gz (every result file but checkpoints, plus session.log and bench.md) and one
# $OUT/resume-<i>.tar per unfinished run's checkpoint, renewed each time a run finishes, so a command stopped before
# its end still returns the runs finished before. Here: `gpu_local.py unpack` (above), then `bati experiment E --scale
# paper --report-only --out-dir results/paper/experiments` for each E of EXPERIMENTS, and `bati claims`.
# FILL=kuhn (an experiment): while the first family's data is collected, FILL's family (FILL_FAMILY, default
# KuhnPoker) is collected on FILL_WORKERS cores (default 4; the family gets the others) and trains FILL's methods
# one job at a time on the idle GPU. On one core Kuhn's data took 70.8 s, as long as HalfCheetahDir's on 15 (H200),
# so no Kuhn job began; on 4 it took 28.1 s.
# CPU dry run: MODE=fg SCALE=quick METHODS=bati SEEDS="0 1" SETTINGS="steps=200" DATA=... bash this file.
set -u
mode=${MODE:-fg}
scale=${SCALE:-paper}
families=${FAMILIES:-AntDir}
# The claim methods first (C1-C3 compare BATI with these four), then the references; 3 seeds (the claims' minimum):
# such a job takes 1.5-3 minutes on an H100 or H200 (docs/performance.md), and the committed cells are skipped. BATI-R and
# BATI-auto cost only evaluations where BATI's job is pending too (test-time rules of its run: docs/methods.md).
methods=${METHODS:-"bati focal csro recon unicorn oracle bati-r bati-auto no-context"}
# EXPERIMENTS: `bati experiment` names run per family in this order (default main); each runs the methods of METHODS
# it has on the family (e.g. EXPERIMENTS='main noise' METHODS='bati focal': claim C4's pair at eps 0 / 0.5 on AntDir
# and HalfCheetahDir, their eps-1 cells being main's); an experiment collects the data it needs over all cores.
experiments=${EXPERIMENTS:-main}
seeds=${SEEDS:-"0 1 2"}
workers=${WORKERS:-1}
cores=$(nproc)
eval_workers=${EVAL_WORKERS:-$((cores > 5 ? cores - 4 : 1))}
# evaluation (CPU MuJoCo, 10-40% of a job) runs in a thread while the GPU trains on (TrainConfig.eval_beside_training)
settings="eval_workers=$eval_workers eval_beside_training=true${SETTINGS:+ $SETTINGS}"
budget=${BUDGET_S:-540}
watch=${WATCH_S:-540}
data=${DATA:-/tmp/bati-data}
results=${RESULTS:-/tmp/bati-results}
out=${OUT:-/tmp/bati-out}
start=$(date +%s)
mkdir -p "$out" "$results"

install() {
  if ! python3 -c "import mujoco, gymnasium, minari, tyro, rliable" 2>/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
      .whl/*.whl || { echo "no wheels to install: run scripts/gpu_wheels.sh where there is an index and copy .whl along"; exit 2; }
    export PYTHONPATH=/tmp/site
  fi
  export PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH} MUJOCO_GL=${MUJOCO_GL:-glfw} \
    XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
  # everything the work imports, checked in seconds rather than found missing minutes later
  python3 -c "import mujoco, gymnasium, minari, tyro, bati.cli; from bati.report.stats import require_rliable
require_rliable()" || { echo "the machine lacks a package the work needs (above): add its wheel in gpu_wheels.sh"; exit 2; }
}

collect() {  # $1 family, $2 workers
  python3 -m bati.cli data collect --family "$1" --scale "$data_scale" --workers "$2" --root "$data" \
    > "$results/collect-$1.log" 2>&1
}

work() {  # the session's work: benchmark, then family after family
  data_scale=paper; [ "$scale" = quick ] && data_scale=quick
  set -- $families
  if [ -n "${BENCH:-}" ]; then
    taskset -c 0 python3 benchmarks/seed_throughput.py --family "$1" --method bati --scale "$scale" \
      --seeds ${BENCH_SEEDS:-3} --length "${BENCH_LENGTH:-100}" --chunks 3 > "$results/bench.md" 2>&1 &
    bench=$!
    collect "$1" $((cores > 1 ? cores - 1 : 1)); echo "$1 data (rc $?) after $(( $(date +%s) - start )) s"
    wait "$bench"; echo "benchmark (rc $?) after $(( $(date +%s) - start )) s"; cat "$results/bench.md"
  elif [ -n "${FILL:-}" ]; then
    fill_workers=$(( ${FILL_WORKERS:-4} < cores ? ${FILL_WORKERS:-4} : 1 ))
    collect "$1" $((cores > fill_workers ? cores - fill_workers : 1)) &
    first=$!
    fill "$first"
    wait "$first"; echo "$1 data (rc $?) after $(( $(date +%s) - start )) s"
  else
    collect "$1" "$cores"; echo "$1 data (rc $?) after $(( $(date +%s) - start )) s"
  fi
  while [ $# -gt 0 ]; do
    family=$1; shift
    [ $# -gt 0 ] && { (renice -n 10 "$BASHPID" > /dev/null; collect "$1" $((cores / 4 > 0 ? cores / 4 : 1))) & }
    for experiment in $experiments; do
      chosen=$(chosen_methods "$experiment" "$family") || { echo "no experiment $experiment: stopping"; break 2; }
      [ -z "$chosen" ] && { echo "$experiment has none of the methods on $family: skipped"; continue; }
      # shellcheck disable=SC2086  # word lists on purpose
      run_experiment "$experiment" "$family" $chosen
      [ $? -eq 2 ] && { echo "bad input: the other families would fail alike; stopping"; break 2; }
    done
    wait  # the next family's data
  done
  echo "all done after $(( $(date +%s) - start )) s"; touch "$results/session.done"
}

chosen_methods() {  # $1 experiment, $2 family: the methods of METHODS it runs there, in METHODS' order (maybe none)
  # shellcheck disable=SC2086
  python3 - "$1" "$2" $methods << 'EOF'
import sys
from bati.experiments.specs import get_spec
experiment, family, methods = sys.argv[1], sys.argv[2], sys.argv[3:]
have = {m for part in get_spec(experiment).parts if family in part.families for m in part.methods}
print(" ".join(m for m in methods if m in have))
EOF
}

run_experiment() {  # $1 experiment, $2 family, then its methods: one `bati experiment` (finished cells skipped)
  local experiment=$1 family=$2 rc
  shift 2
  local log="$results/experiment-$experiment-$family.log"
  # shellcheck disable=SC2086
  python3 -m bati.cli experiment "$experiment" --scale "$scale" --families "$family" --methods "$@" \
    --seeds $seeds --workers "$workers" --data-root "$data" --out-dir "$results" --settings $settings >> "$log" 2>&1
  rc=$?; echo "$family $experiment ($*) exit $rc after $(( $(date +%s) - start )) s"; tail -2 "$log"
  return $rc
}

fill() {  # $1: the pid of the first family's collection. The GPU idles meanwhile (~100-135 s for a MuJoCo family),
  # so FILL's experiment on FILL_FAMILY (default KuhnPoker, whose data takes ~70 s on one core) runs one method's
  # job at a time until that collection ends; the first family then waits for the job at hand only.
  local family=${FILL_FAMILY:-KuhnPoker} method rc
  collect "$family" "$fill_workers"; rc=$?; echo "$family data for $FILL (rc $rc) after $(( $(date +%s) - start )) s"
  # one line and no jobs when the data cannot be had (without OpenSpiel, 8 jobs once failed one by one)
  [ "$rc" -eq 0 ] || { tail -1 "$results/collect-$family.log"; echo "no $FILL fill"; return; }
  for method in $(chosen_methods "$FILL" "$family"); do
    kill -0 "$1" 2> /dev/null || break
    run_experiment "$FILL" "$family" "$method"
  done
}

seed_results() {  # the committed cells of this scale count as finished here too: the sweep skips them; the unfinished
  # runs of earlier machines (.gpu/resume: scripts/gpu_local.py unpack) resume from their checkpoints
  local committed=${COMMITTED:-results/$scale/experiments} resume=${RESUME:-.gpu/resume}
  [ -z "${COMMITTED:-}" ] && [ -d .gpu/committed ] && committed=.gpu/committed  # gpu_local.py away's slim copy
  if [ -d "$committed" ]; then
    cp -a "$committed/." "$results/"
    echo "$(find "$committed" -name eval.json | wc -l) committed run(s) of $committed count as finished"
  fi
  if [ -d "$resume" ]; then
    cp -a "$resume/." "$results/"
    echo "$(find "$resume" -name checkpoint.msgpack | wc -l) unfinished run(s) of $resume resume from their checkpoints"
  fi
}

finished() { find "$results" -name eval.json | wc -l; }

pack() {  # one pack at a time, replaced atomically: a command stopped before its end still leaves the last one
  local pack="$out/results.tar.gz"
  # tar exits 1 when a log grew while it was read (a running job's metrics): the pack is still whole
  tar czf "$pack.part" --warning=no-file-changed --exclude=checkpoint.msgpack --exclude='*.lock' --exclude='.*.tmp' \
    -C "$results" .
  [ $? -le 1 ] && mv "$pack.part" "$pack"
  pack_resume
  echo "packed $(finished) finished run(s) into $pack ($(du -h "$pack" | cut -f1)), $(ls "$out" | grep -c '^resume-')" \
    "checkpoint(s) of unfinished runs, after $(( $(date +%s) - start )) s"
}

pack_resume() {  # the checkpoint of each unfinished run, a file each (~4-5 MB at the paper scale: small files to copy
  # back), its logs being in the results pack: the next machine gets them back (gpu_local.py unpack puts them in
  # .gpu/resume) and resumes those runs instead of restarting them at step 0
  local i=0 checkpoint
  while IFS= read -r checkpoint; do
    [ -e "$(dirname "$checkpoint")/eval.json" ] && continue
    [ $i -ge "${RESUME_FILES:-3}" ] && { echo "more unfinished runs than RESUME_FILES: the others restart" >&2; break; }
    tar cf "$out/resume-$i.tar.part" -C "$results" "${checkpoint#"$results"/}" && mv "$out/resume-$i.tar.part" "$out/resume-$i.tar"
    i=$((i + 1))
  done < <(find "$results" -name checkpoint.msgpack | sort)
  while [ -e "$out/resume-$i.tar" ]; do rm -f "$out/resume-$i.tar"; i=$((i + 1)); done  # an earlier pack's extra ones
}

watch_work() {  # until the detached work is done or WATCH_S has passed; packs each time a run finishes
  local packed=-1
  while [ ! -e "$results/session.done" ] && [ $(( $(date +%s) - start )) -lt "$watch" ]; do
    [ "$(finished)" != "$packed" ] && { packed=$(finished); pack > /dev/null; }
    sleep 5
  done
  cat "$results/session.log"; nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null
  pack
}

case $mode in
  start)
    install
    [ -e "$results/session.log" ] && { echo "work already started here: use MODE=watch"; exit 2; }
    seed_results
    export -f work collect chosen_methods run_experiment fill
    export scale families experiments methods seeds workers settings data results start cores BENCH FILL FILL_FAMILY
    setsid nohup bash -c work > "$results/session.log" 2>&1 < /dev/null &
    watch_work;;
  watch)
    [ -e "$results/session.log" ] || { echo "no detached work on this machine (a fresh one?): use MODE=start"; exit 2; }
    watch_work;;
  fg)
    install
    seed_results
    set -m  # the work gets its own process group: the budget stops its worker processes too
    work > "$results/session.log" 2>&1 &
    job=$!
    ( sleep "$budget"; kill -TERM -- -"$job"; sleep 20; kill -KILL -- -"$job" ) >/dev/null 2>&1 </dev/null &
    watchdog=$!
    wait "$job"; rc=$?
    kill -- -"$watchdog" 2>/dev/null  # its sleep too: nothing may outlive the command
    set +m
    echo "work exit $rc after $(( $(date +%s) - start )) s (143 or 137: stopped at the budget; run again to resume)"
    cat "$results/session.log"; pack;;
  pack)  # only the packing (what a watch call ends with): RESULTS into OUT
    pack;;
  *) echo "MODE must be start, watch, fg or pack, not $mode"; exit 2;;
esac
