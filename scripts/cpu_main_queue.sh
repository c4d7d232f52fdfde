#!/usr/bin/env bash
# The cpu-scale main table (issue 30), one family and one method at a time, in the background:
#   PYTHONPATH=$PWD/src nohup nice bash scripts/cpu_main_queue.sh /work/run-data /work/main/results/cpu/experiments \
#       > cpu-queue.log 2>&1 &   (PYTHONPATH: this checkout's code, not the editable install's)
# Each line is a resumable `bati experiment`: finished cells are skipped (in seconds), an interrupted job resumes
# from its checkpoints (a run checkpoints at least every 10 minutes). Run it from an archive of a fixed commit
# (git worktree add ../bg-<commit> <commit>) so that the code does not change under a running job; results go into
# this checkout's results/cpu/experiments.
# Order: claims first. A 3-seed job costs ~1 h on this project's 2-core machine (ER-TRL ~4 h, Recon ~2 h, with other
# work on the cores), so the table takes many sessions: phase 1 runs, family by family, the methods that the claims
# C1-C3 compare (BATI, its reward-only variant, the paper's baselines, the Oracle and the no-context floor); phase 2
# the others (ER-TRL, BATI-auto, DPT at one seed is the experiment's own choice).
# After a job: `bati experiment main --scale cpu --report-only --out-dir results/cpu/experiments --data-root DATA`
# and `bati claims` regenerate the report and docs/claims.md; commit the cells (checkpoints are git-ignored).
set -u
data_root=${1:-data}
out_dir=${2:-$(pwd)/results/cpu/experiments}
families=${FAMILIES:-"AntDir HalfCheetahVel HalfCheetahDir HopperParam WalkerParam"}
phase1=${PHASE1:-"oracle bati bati-r focal csro unicorn recon no-context"}
phase2=${PHASE2:-"er-trl bati-auto dpt"}
# Phase 0: jobs a stop interrupted (a main-table cell with a checkpoint and no eval.json) finish first.
interrupted=$(for ckpt in "$out_dir"/*/cpu-eps1-*/*-seed*/checkpoint.msgpack; do
  [ -e "$ckpt" ] || continue; run=$(dirname "$ckpt"); [ -e "$run/eval.json" ] && continue
  echo "$(basename "$(dirname "$(dirname "$run")")"):$(basename "$run" | sed 's/-seed[0-9]*$//')"
done | sort -u)
for job in $interrupted; do
  family=${job%%:*}; method=${job#*:}
  echo "=== $family $method (interrupted) $(date -u)"
  python -m bati.cli experiment main --scale cpu --families "$family" --methods "$method" \
    --out-dir "$out_dir" --data-root "$data_root" --workers 1
  echo "=== $family $method done rc=$? $(date -u)"
done
# FOCAL's distance as its code lineage computes it (docs/methods.md, "FOCAL"), on AntDir: does it change the
# baselines' fall on p_test? Its own output directory, so the main table's report is not touched.
if [ -z "${SKIP_ABLATIONS:-}" ]; then
  echo "=== AntDir focal distance=root-mean $(date -u)"
  python -m bati.cli experiment main --scale cpu --families AntDir --methods focal --settings focal.distance=root-mean \
    --out-dir "$(dirname "$out_dir")/focal-distance" --data-root "$data_root" --workers 1
  echo "=== AntDir focal distance=root-mean done rc=$? $(date -u)"
fi
for methods in "$phase1" "$phase2"; do
  for family in $families; do
    python -m bati.cli data collect --family "$family" --scale paper --workers 2 --root "$data_root" || exit 1
    for method in $methods; do
      echo "=== $family $method $(date -u)"
      python -m bati.cli experiment main --scale cpu --families "$family" --methods "$method" \
        --out-dir "$out_dir" --data-root "$data_root" --workers 1
      echo "=== $family $method done rc=$? $(date -u)"
    done
  done
done
