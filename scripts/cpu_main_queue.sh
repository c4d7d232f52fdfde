#!/usr/bin/env bash
# The cpu-scale main table (issue 30), one family and one method at a time, in the background:
#   PYTHONPATH=$PWD/src nohup nice bash scripts/cpu_main_queue.sh /work/run-data /work/main/results/cpu/experiments \
#       > cpu-queue.log 2>&1 &   (PYTHONPATH: this checkout's code, not the editable install's)
# Each line is a resumable `bati experiment`: finished cells are skipped, an interrupted job resumes from its
# checkpoints. Run it from an archive of a fixed commit (git worktree add ../bg-<commit> <commit>) so that the
# code does not change under a running job; results go into this checkout's results/cpu/experiments.
# After a job: `bati experiment main --scale cpu --report-only --out-dir results/cpu/experiments --data-root DATA`
# and `bati claims` regenerate the report and docs/claims.md; commit the cells (checkpoints are git-ignored).
set -u
data_root=${1:-data}
out_dir=${2:-$(pwd)/results/cpu/experiments}
families=${FAMILIES:-"AntDir HalfCheetahVel HalfCheetahDir HopperParam WalkerParam"}
methods=${METHODS:-"oracle bati bati-r recon focal unicorn no-context er-trl csro bati-auto dpt"}  # CSRO re-queued after its CLUB fix
for family in $families; do
  python -m bati.cli data collect --family "$family" --scale paper --workers 2 --root "$data_root" || exit 1
  for method in $methods; do
    echo "=== $family $method $(date -u)"
    python -m bati.cli experiment main --scale cpu --families "$family" --methods "$method" \
      --out-dir "$out_dir" --data-root "$data_root" --workers 1
    echo "=== $family $method done rc=$? $(date -u)"
  done
done
