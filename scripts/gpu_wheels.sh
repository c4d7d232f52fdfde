#!/usr/bin/env bash
# Wheels of what the lent GPU machine's image lacks (issue 29; its Python is 3.12, no package index there),
# downloaded here into .whl/ (git-ignored through .git/info/exclude), ~26 MB. Carry `.whl` in each device call;
# scripts/gpu_paper_scale.sh installs them there. Versions: the ones this project's CI installs (pip show).
set -euo pipefail
cd "$(dirname "$0")/.."
exclude="$(git rev-parse --git-dir)/info/exclude"
mkdir -p "$(dirname "$exclude")" .whl
grep -qx '/.whl/' "$exclude" 2>/dev/null || echo '/.whl/' >> "$exclude"
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl \
  mujoco==4.0.0 mujoco-core==4.0.0 mujoco-studio==4.0.0 websockets==15.0.1 glfw==2.11.0 pyopengl==3.1.10 \
  gymnasium==1.4.0 farama-notifications==0.0.6 minari==0.5.4 tyro==1.0.17 docstring-parser==0.18.0 typeguard==4.6.1
du -sh .whl
