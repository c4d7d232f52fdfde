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
# C1-C3 compare (BATI, its reward-only variant, the paper's baselines, the Oracle and the no-context floor), then the
# AntDir noise ablation (C4), then phase 2: the others (ER-TRL, BATI-auto, DPT) on every family.
# After a job: `bati experiment main --scale cpu --report-only --out-dir results/cpu/experiments --data-root DATA`
# and `bati claims` regenerate the report and docs/claims.md; commit the cells (checkpoints are git-ignored).
set -u
data_root=${1:-data}
out_dir=${2:-$(pwd)/results/cpu/experiments}
families=${FAMILIES:-"AntDir HalfCheetahVel HalfCheetahDir HopperParam WalkerParam"}
phase1=${PHASE1:-"oracle bati bati-r focal csro unicorn recon no-context"}
phase2=${PHASE2:-"er-trl bati-auto dpt"}
# Phase 0: jobs a stop interrupted (a cell with a checkpoint and no eval.json) finish first: eps = 1 cells are the
# main table's, the others the noise ablation's.
interrupted=$(for ckpt in "$out_dir"/*/cpu-eps*/*-seed*/checkpoint.msgpack; do
  [ -e "$ckpt" ] || continue; run=$(dirname "$ckpt"); [ -e "$run/eval.json" ] && continue
  setting=$(basename "$(dirname "$run")"); experiment=noise; case $setting in cpu-eps1-*) experiment=main;; esac
  echo "$experiment:$(basename "$(dirname "$(dirname "$run")")"):$(basename "$run" | sed 's/-seed[0-9]*$//')"
done | sort -u)
for job in $interrupted; do
  IFS=: read -r experiment family method <<< "$job"
  echo "=== $family $method ($experiment, interrupted) $(date -u)"
  python -m bati.cli experiment "$experiment" --scale cpu --families "$family" --methods "$method" \
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
main_phase() {  # $1: the methods, each on every family
  for family in $families; do
    python -m bati.cli data collect --family "$family" --scale paper --workers 2 --root "$data_root" || exit 1
    for method in $1; do
      echo "=== $family $method $(date -u)"
      python -m bati.cli experiment main --scale cpu --families "$family" --methods "$method" \
        --out-dir "$out_dir" --data-root "$data_root" --workers 1
      echo "=== $family $method done rc=$? $(date -u)"
    done
  done
}
main_phase "$phase1"
# Claim C4 (noise hurts the baselines, not BATI): the AntDir noise ablation, eps 0 and 0.5 (eps 1's cells are the
# main table's); ER-TRL's part of it last (issue 28).
for noise in 0 0.5; do
  python -m bati.cli data collect --family AntDir --scale paper --noise "$noise" --workers 2 --root "$data_root" || exit 1
done
for method in ${NOISE_METHODS:-"bati bati-r focal csro unicorn recon er-trl"}; do
  echo "=== AntDir noise $method $(date -u)"
  python -m bati.cli experiment noise --scale cpu --families AntDir --methods "$method" \
    --out-dir "$out_dir" --data-root "$data_root" --workers 1
  echo "=== AntDir noise $method done rc=$? $(date -u)"
done
main_phase "$phase2"
