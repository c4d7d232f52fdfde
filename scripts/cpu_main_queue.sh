#!/usr/bin/env bash
# The cpu-scale main table, one family and one method at a time, in the background:
#   git worktree add ../bg-<commit> <commit>    # the code of a fixed commit (it must not change under a running job)
#   cd <this checkout> && PYTHONPATH=../bg-<commit>/src nohup nice bash ../bg-<commit>/scripts/cpu_main_queue.sh \
#       /work/run-data results/cpu/experiments > cpu-queue.log 2>&1 &
# (PYTHONPATH: the worktree's code, not the editable install's; run from this checkout with a relative out dir, so
# that the reports and sweep files it writes name `results/cpu/experiments` as a rerun here would, not an absolute
# path; each run records the commit of the code it ran, the worktree's.)
# Each line is a resumable `bati experiment`: finished cells are skipped (those finished when the queue starts
# without starting bati at all: ~10 s a job, minutes for a restart beside ~40 finished jobs), an interrupted job resumes
# from its checkpoints (a run checkpoints at least every 10 minutes) when the machine still holds them. Every job
# trains one seed: a work session lasts 3 hours, often on a fresh machine (checkpoints are git-ignored; when the
# machine does outlive a session, phase 0 below resumes its cut job), so a job should finish inside one; on 2 cores one seed at a time is also no slower than three vmapped seeds
# (AntDir ER-TRL at the cpu scale: 40.0 ms per step for one seed, 135.6 ms for three; docs/performance.md).
# Order: claims first. A seed costs 12-16 min on free cores (6.9-7.7 ms per step for BATI, docs/performance.md) and
# 20-80 min with other work beside (IQL alone ~20 min; CSRO and ER-TRL ~1-1.3 h, Recon and BATI-R ~45 min), so the
# table takes many sessions: AntDir's last paper baseline (CSRO) and ER-TRL, the AntDir noise ablation's
# BATI and FOCAL (claim C4, untested at every scale), then phase 1 in two passes over the families: the Oracle (the
# normaliser), BATI and FOCAL first (claims C1-C2 on five families; BATI-R and BATI-auto are test-time rules of
# BATI's run, which is their training too: `bati+bati-r+bati-auto`), with the context-length and ood-tasks
# ablations' BATI and FOCAL (claims C5, C6) before the last two families, then the other methods that the claims
# compare (Recon first, the paper's other baselines, BATI's reward-only variant hosting BATI-auto where BATI's run is
# finished, the no-context floor) and the two
# ablations' other baselines, then the noise ablation's other methods and ER-TRL's noise cells (since 2026-11-27:
# they were before phase 1b, but decide no paper claim), the FOCAL distance ablation, then
# phase 2: the others (ER-TRL, BATI-auto, DPT) on every family. WAIT_PID: a running job's process to wait for first
# (a queue restarted with a new order beside a job of the old one).
# Overrides (space-separated lists; ' ' for none): FAMILIES (phases 1-2; e.g. only the families whose paper data
# the machine holds, so that no session goes to a collection), PHASE1A, PHASE1B, PHASE2 (methods per family),
# NOISE_FIRST, NOISE_REST, NOISE_NEXT (the noise ablation's methods), SEEDS, SKIP_ABLATIONS=1.
# After a job: `bati experiment main --scale cpu --report-only --out-dir results/cpu/experiments --data-root DATA`
# and `bati claims` regenerate the report and docs/claims.md; commit the cells (checkpoints are git-ignored).
# A one-seed job's own report covers its seed only: before committing, revert the report and sweep files alone
# (`git checkout -- results/cpu/experiments/main results/cpu/experiments/*.sweep.json`), never a run directory:
# a committed partial log of a cut run would overwrite the finished run's own (it happened on 2026-11-27).
# STOP_AT (epoch seconds, e.g. STOP_AT=$(date -d '+170 min' +%s)): the session's end. A seed or a collection whose
# estimate (minutes below: measured on this project's 2-core machines with other work beside, docs/performance.md)
# would not finish by then is skipped, and the queue goes on to the next that fits: a job cut by the end of a
# session is lost with its machine. The skipped ones come first again in the next session (finished cells are
# skipped in seconds). PACE (percent, default 100): scales those estimates, e.g. PACE=50 when nothing else will use
# the cores (a seed on free cores takes about half: AntDir BATI 12-16 min, ER-TRL 38-44 min; results/cpu/experiments).
set -u
while [ -n "${WAIT_PID:-}" ] && kill -0 "$WAIT_PID" 2> /dev/null; do sleep 20; done
stop_at=${STOP_AT:-}
minutes() {  # a seed's (or, "collect", a family's paper data) estimated minutes
  case $1 in
    bati+*|bati-r+*) echo 70;;  # BATI (or BATI-R) with the others of its training as test-time rules
    oracle|no-context) echo 35;; focal|unicorn) echo 45;; bati|bati-r|bati-auto|recon) echo 65;;
    csro|er-trl) echo 100;; collect) echo 40;;
    dpt) echo 190;;  # 114 ms per step beside an ER-TRL job (benchmarks/train_step.py, 2026-11-28): more than a session
    *) echo 100;;
  esac
}
fits() {  # $1: what (a method, or collect), $2: how many cells (default 1); true when they would finish before STOP_AT
  [ -z "$stop_at" ] && return 0
  local need=$(( ${2:-1} * $(minutes "$1") * ${PACE:-100} / 100 ))
  [ $(( $(date +%s) + 60 * need )) -le "$stop_at" ] && return 0
  echo "=== skipped: $1 ($need min) would not finish before STOP_AT $(date -u -d "@$stop_at") $(date -u)"
  return 1
}
# The paper data a family's jobs need is collected when the first of them is to run, not before: a fresh machine
# has no data, and a family (or a noise setting) whose jobs are all finished costs no collection (~15-40 min each).
needs=()  # the paper data the next jobs need, "family [options]" each: set before a family's jobs, emptied once at hand
have_data() {  # collects what `needs` names and is missing; false when a collection would not finish before STOP_AT
  local want
  for want in "${needs[@]}"; do
    # shellcheck disable=SC2086  # "family --noise e": split into the options
    python -m bati.cli data info --scale paper --root "$data_root" --family $want > /dev/null 2>&1 && continue
    fits collect || return 1
    echo "=== collect $want $(date -u)"
    python -m bati.cli data collect --scale paper --workers 2 --root "$data_root" --family $want || exit 1
  done
  needs=()  # collected: the family's later jobs need no check
}
data_root=${1:-data}
out_dir=${2:-$(pwd)/results/cpu/experiments}
seeds=${SEEDS:-"0 1 2"}
job() {  # $1 experiment, $2 family, $3 method (a+b: methods of one training, e.g. bati+bati-r), the rest: more
  # options; one seed at a time
  local experiment=$1 family=$2 method=$3 ran=; shift 3
  local cells=1; [ "$experiment" = noise ] && cells=2  # a noise seed trains eps 0 and eps / 2 (eps's are main's)
  for seed in $seeds; do
    local methods=${method//+/ }
    # test-time rules of the first one's run (bati+bati-r+bati-auto) come with it only while its run is
    # to do: beside a finished one they would train on their own, which their own later pass does (main: phase 1b;
    # the ablations: their second pass). Asked of the plans now: the run may have finished since the queue started.
    local first=${methods%% *}
    # (the Python only where some setting of the family has such a run finished: seconds saved per job otherwise)
    [ "$methods" != "$first" ] && ls "$out_dir/$family/"*/"$first-seed$seed/eval.json" > /dev/null 2>&1 &&
      finished_now "$experiment" "$family" "$seed" "$first" && methods=$first
    # finished at the queue's start (its own plans, below): skipped here, without a `bati experiment` to say so
    [ "$*" = "--out-dir $out_dir" ] && finished "$experiment" "$family" "$seed" $methods && continue
    fits "${methods// /+}" "$cells" || continue
    have_data || continue
    echo "=== $family ${methods// /+} seed $seed ($experiment $*) $(date -u)"
    python -m bati.cli experiment "$experiment" --scale cpu --families "$family" --methods $methods --seeds "$seed" \
      --data-root "$data_root" --workers 1 "$@"
    echo "=== $family ${methods// /+} seed $seed done rc=$? $(date -u)"
    ran=1
  done  # the report over every seed finished so far (a one-seed job reports its seed only)
  [ -n "$ran" ] && python -m bati.cli experiment "$experiment" --scale cpu --report-only --data-root "$data_root" \
    "$@" > /dev/null
  return 0
}
finished_now() {  # $1 experiment, $2 family, $3 seed, $4 method: true when its planned cells are finished now
  python - "$out_dir" "$data_root" "$@" << 'EOF'
import sys
from pathlib import Path
from bati.experiments.pipeline import plan_experiment
from bati.experiments.specs import get_spec
from bati.experiments.sweep import finished as is_done
out_dir, data_root, experiment, family, seed, method = sys.argv[1:]
plan = plan_experiment(get_spec(experiment), "cpu", Path(out_dir), seeds=(int(seed),), methods=(method,),
                       families=(family,), data_root=Path(data_root))
sys.exit(0 if all(map(is_done, plan.cells)) else 1)
EOF
}
finished() {  # $1 experiment, $2 family, $3 seed, the rest: methods; true when all their planned cells were finished
  local experiment=$1 family=$2 seed=$3 m; shift 3
  for m in "$@"; do case " $finished_cells " in *" $experiment:$family:$m:$seed "*) ;; *) return 1;; esac; done
}
families=${FAMILIES:-"AntDir HalfCheetahVel HalfCheetahDir HopperParam WalkerParam"}
phase1a=${PHASE1A:-"oracle bati+bati-r+bati-auto focal"}
phase1b=${PHASE1B:-"recon unicorn csro bati-r+bati-auto no-context"}  # bati-r hosts bati-auto where bati finished
phase2=${PHASE2:-"er-trl bati-auto dpt"}
# The queue's experiments as planned at the cpu scale: which (experiment, family, method, seed) have all their cells
# finished (eval.json; a job of those is skipped without starting Python), and phase 0: jobs a stop interrupted (a cell
# with a checkpoint and no eval.json) finish first, each in the first experiment whose plan holds its run directory.
plans=$(python - "$out_dir" "$data_root" << 'EOF'
import sys
from pathlib import Path
from bati.experiments.pipeline import plan_experiment
from bati.experiments.specs import get_spec
from bati.experiments.sweep import finished as is_done
out_dir, data_root = Path(sys.argv[1]), Path(sys.argv[2])
runs = {p.parent.resolve() for p in out_dir.glob("*/*/*-seed*/checkpoint.msgpack") if not (p.parent / "eval.json").exists()}


for name in ("main", "noise", "context-length", "ood-tasks"):
    done = {}
    for cell in plan_experiment(get_spec(name), "cpu", out_dir, seeds=(0, 1, 2, 3, 4), data_root=data_root).cells:
        c = cell.config
        key = f"{name}:{c.family}:{c.method}:{c.seed}"
        done[key] = done.get(key, True) and is_done(cell)
        if c.out_dir.resolve() in runs:
            runs.discard(c.out_dir.resolve())
            print(f"cut:{name}:{c.family}:{c.method}:{c.seed}")  # resumed with the test-time rules it began with
    print(*(f"finished:{key}" for key, value in done.items() if value), sep="\n")
EOF
)
finished_cells=$(sed -n 's/^finished://p' <<< "$plans" | tr '\n' ' ')
interrupted=$(sed -n 's/^cut://p' <<< "$plans" | sort -u)
for job in $interrupted; do  # the cut seed only (the sweep resumes it with the rules it began with); other seeds later
  IFS=: read -r experiment family method seed <<< "$job"
  seeds=$seed job "$experiment" "$family" "$method" --out-dir "$out_dir"
done
needs=(AntDir)
for method in csro er-trl; do job main AntDir "$method" --out-dir "$out_dir"; done
noise() {  # $@: the methods of the AntDir noise ablation to run (eps 0 and 0.5; eps 1's cells are the main table's)
  needs=("AntDir --noise 0" "AntDir --noise 0.5")
  for method in "$@"; do job noise AntDir "$method" --out-dir "$out_dir"; done
}
main_phase() {  # $1: the methods, each on every family (or on the families $2)
  for family in ${2:-$families}; do
    needs=("$family")
    for method in $1; do job main "$family" "$method" --out-dir "$out_dir"; done
  done
}
# Claim C4 (noise hurts the baselines, not BATI) is untested at every scale: the AntDir noise ablation's claim pair
# (BATI and FOCAL, the baseline whose fall on p_test is decided on AntDir) comes first. Then phase 1 in two passes:
# the claim pair with the Oracle (the normaliser) on every family, so that C1-C2 rest on five families as early as
# possible, then the other paper methods (Recon first: claim C3), then the ablations' and the noise ablation's other
# baselines; ER-TRL's part of the noise ablation (beyond the paper: it decides no paper claim) after them.
noise ${NOISE_FIRST:-bati focal}
main_phase "$phase1a" "AntDir HalfCheetahVel HalfCheetahDir"  # the families whose data is at hand
# Claims C5 (Table 1: BATI gains from longer contexts, the baselines do not) and C6 (Table 2: only BATI positive on
# out-of-range AntDir tasks), untested at every scale with 3 seeds: their claim pair (BATI, with BATI-R evaluated
# as rules of its run, and FOCAL) before the last two families' data; their other baselines come with phase 1b's.
ablations() {  # $@: the methods of each of the two ablations
  [ -n "${SKIP_ABLATIONS:-}" ] && return
  needs=()  # their data (other noise settings) is collected by their sweeps
  for method in "$@"; do job context-length HalfCheetahDir "$method" --out-dir "$out_dir"; done
  for method in "$@"; do job ood-tasks AntDir "$method" --out-dir "$out_dir"; done
}
ablations bati+bati-r focal
main_phase "$phase1a"
main_phase "$phase1b"
ablations csro unicorn recon bati-r  # bati-r: the seeds whose BATI run finished without it as a rule
noise ${NOISE_REST:-bati-r csro unicorn recon}
noise ${NOISE_NEXT:-er-trl}
# FOCAL's distance as its code lineage computes it (docs/methods.md, "FOCAL"), on AntDir: does it change the
# baselines' fall on p_test? Its own output directory, so the main table's report is not touched.
if [ -z "${SKIP_ABLATIONS:-}" ]; then
  needs=(AntDir)
  job main AntDir focal --settings focal.distance=root-mean --out-dir "$(dirname "$out_dir")/focal-distance"
fi
main_phase "$phase2"
