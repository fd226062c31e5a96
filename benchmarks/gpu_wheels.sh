#!/usr/bin/env bash
# Prepare, on the CPU machine, the wheels `benchmarks/gpu_call.sh` installs on a GPU machine that
# cannot reach a package index (the H200 lent to tt's sessions has Python 3.12 and its own CUDA
# torch, but no Warp, MuJoCo, MuJoCo-Warp, Newton, mink, zarr or cma). Versions are the pins of
# constraints.txt; torch and numpy stay the machine's. Files land in .whl/ (git-ignored; a
# call names it in `carry`), split into pieces of at most $PIECE bytes, because one call carries at most
# 64 MiB of working tree (the tracked repo is ~30 MB of it) and warp-lang's wheel alone is 149 MB:
# carry them over several calls with `gpu_call.sh stage` (see there).
set -euo pipefail
cd "$(dirname "$0")/.."
PIECE=${PIECE:-30000000}
pin() { grep -E "^$1==" constraints.txt | head -1; }
mkdir -p .whl/full
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl/full \
  "$(pin warp-lang)" "$(pin mujoco)" "$(pin mujoco-warp)" "$(pin newton)" "$(pin mink)" "$(pin cma)" "$(pin zarr)" \
  numcodecs donfig google-crc32c qpsolvers daqp glfw pyopengl websockets etils importlib_resources
# Pieces of at most PIECE bytes; gpu_call.sh joins NAME.whl.part-* back into NAME.whl.
rm -f .whl/*.part-* .whl/*.whl
for w in .whl/full/*.whl; do
  if [ "$(stat -c %s "$w")" -gt "$PIECE" ]; then split -b "$PIECE" -d "$w" ".whl/$(basename "$w").part-"; else cp "$w" .whl/; fi
done
rm -rf .whl/full
ls -la .whl
