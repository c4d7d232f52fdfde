#!/usr/bin/env bash
# One device call's worth of the paper scale on a lent GPU machine (issue 29). Run it there as the whole command:
#   run(command="FAMILIES=AntDir bash scripts/gpu_paper_scale.sh", carry=[".whl"], timeout_s=600)
# after `bash scripts/gpu_wheels.sh` here. It installs the wheels (when the machine lacks MuJoCo), collects the
# families' paper data over all cores, trains `bati experiment main` at SCALE for FAMILIES x METHODS x SEEDS with
# WORKERS jobs at a time (evaluation is CPU MuJoCo: parallel jobs keep the GPU busy), stops before BUDGET_S
# (a killed job resumes from its last checkpoint on the next call while the machine is still warm; a bare
# machine starts the job again), and packs every result file but the checkpoints into
# $OUT/results-<stamp>.tar.gz. Here: tar xzf it into results/<scale>/experiments, then
# `bati experiment main --scale paper --report-only --out-dir results/paper/experiments` and `bati claims`.
# A CPU dry run of the same path: SCALE=quick SETTINGS="steps=200 eval_every=100" DATA=... bash this file.
set -u
scale=${SCALE:-paper}
families=${FAMILIES:-AntDir}
methods=${METHODS:-"oracle bati bati-r recon focal unicorn csro no-context er-trl bati-auto dpt"}
seeds=${SEEDS:-"0 1 2 3 4"}
workers=${WORKERS:-4}
settings=${SETTINGS:-}
budget=${BUDGET_S:-540}
data=${DATA:-/tmp/bati-data}
results=${RESULTS:-/tmp/bati-results}
out=${OUT:-/tmp/bati-out}
start=$(date +%s)
if ! python3 -c "import mujoco, gymnasium, minari, tyro" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || { echo "no wheels to install: run scripts/gpu_wheels.sh here and carry .whl"; exit 2; }
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH} MUJOCO_GL=${MUJOCO_GL:-glfw} XLA_PYTHON_CLIENT_PREALLOCATE=false
mkdir -p "$out" "$results"
data_scale=paper; [ "$scale" = quick ] && data_scale=quick
for family in $families; do
  python3 -m bati.cli data collect --family "$family" --scale $data_scale --workers "$(nproc)" --root "$data" || exit 1
done
echo "data ready after $(( $(date +%s) - start )) s"
left=$(( budget - ($(date +%s) - start) ))
set -m  # the experiment gets its own process group: the budget stops its worker processes too
# shellcheck disable=SC2086  # word lists on purpose
python3 -m bati.cli experiment main --scale "$scale" --families $families --methods $methods --seeds $seeds \
  --workers "$workers" --data-root "$data" --out-dir "$results" ${settings:+--settings $settings} \
  > "$results/experiment.log" 2>&1 &
job=$!
( sleep "$left"; kill -TERM -- -"$job"; sleep 20; kill -KILL -- -"$job" ) >/dev/null 2>&1 </dev/null &
watchdog=$!
wait "$job"; rc=$?
kill -- -"$watchdog" 2>/dev/null  # its sleep too: nothing may outlive the command
set +m
echo "experiment exit $rc after $(( $(date +%s) - start )) s (143 or 137: stopped at the budget; run again to resume)"
tail -3 "$results/experiment.log"
pack="$out/results-$(date -u +%Y%m%dT%H%M%S).tar.gz"
tar czf "$pack" --exclude=checkpoint.msgpack --exclude='*.lock' --exclude='.*.tmp' -C "$results" .
echo "packed $(find "$results" -name eval.json | wc -l) finished run(s) into $pack ($(du -h "$pack" | cut -f1))"
