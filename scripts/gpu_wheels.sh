#!/usr/bin/env bash
# Wheels for a GPU machine without a package index whose Python 3.12 has JAX with CUDA but lacks the rest
# (docs/gpu.md), downloaded here into .whl/ (git-ignored through .git/info/exclude), ~43 MB (16 of it OpenSpiel, for
# KuhnPoker). Copy `.whl` along with the checkout; scripts/gpu_paper_scale.sh installs them there. Versions: the ones
# this project's CI installs (pip show).
set -euo pipefail
cd "$(dirname "$0")/.."
exclude="$(git rev-parse --git-dir)/info/exclude"
mkdir -p "$(dirname "$exclude")" .whl
grep -qx '/.whl/' "$exclude" 2>/dev/null || echo '/.whl/' >> "$exclude"
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl \
  mujoco==4.0.0 mujoco-core==4.0.0 glfw==2.11.0 pyopengl==3.1.10 \
  gymnasium==1.4.0 farama-notifications==0.0.6 minari==0.5.4 tyro==1.0.17 docstring-parser==0.18.0 typeguard==4.6.1 \
  arch==7.2.0 pandas==2.3.3 pytz==2026.6 tzdata==2026.6 \
  open-spiel==2.0.2 ml-collections==1.1.0
# open-spiel (16 MB) and ml-collections: KuhnPoker (FILL=kuhn, the kuhn experiment); without them every Kuhn job
# fails at once ("KuhnPoker needs OpenSpiel").
# Not mujoco-studio (its viewer and renderer, 13 MB) nor websockets: rollouts need neither, and the copy of the
# checkout stays smaller.
# rliable 1.2.0 is an sdist on PyPI: build its (pure-Python) wheel here. The experiment checks for rliable before any
# training (its report needs it); arch 7.2 and pandas < 3 are the versions that work with it (pyproject's `stats`),
# and pandas 2 needs pytz and tzdata, which such an image may lack (without them every experiment stops at once).
python3 -m pip wheel -q --no-deps -w .whl rliable==1.2.0
du -sh .whl
