#!/usr/bin/env bash
# The one prepared GPU call: install tt, run the one-shot benchmark, then a time-boxed online
# training run whose EMA weights come back under $OUT.
#
#   bash benchmarks/gpu_call.sh run     # the call: install, benchmarks/gpu.py, tt train --online
#   bash benchmarks/gpu_call.sh stage   # only copy this call's .whl/ pieces to /tmp/tt_wheels
#
# Installing: tt's pins (constraints.txt) are installed from wheels in .whl/ (made on the CPU
# machine by benchmarks/gpu_wheels.sh), with --no-deps so the machine's CUDA torch and numpy stay;
# tt itself goes in editable with --no-deps. A machine that can reach PyPI needs none of that:
# there `pip install -e '.[test]' -c constraints.txt` (with a CUDA torch) does it, and the script
# uses what is installed. When the pieces exceed one call's carry (64 MiB with the repo), carry
# them over consecutive `stage` calls while the machine stays warm (it is kept about 30 s after a
# call), the last call being `run`; each call names `.whl` in `carry`.
#
# Writes to $OUT (at most 8 files of <= 16 MiB): gpu.md (benchmark), gpu.log, train.log,
# loss.csv, viperx_mini_online_ema.pt (EMA weights, normaliser, config; no optimizer state).
# Time: benchmark <= 8 min (its own budgets) + training $TRAIN_SECONDS (default 90 s) + export,
# so it fits one 10-minute call after a warm install; on a cold machine pass TRAIN_SECONDS=30.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/tt_gpu_out}
STAGE=/tmp/tt_wheels
TRAIN_SECONDS=${TRAIN_SECONDS:-90}
# The recipe of step 2 (default: the generalist on the full space, robot + control). The
# controller's open question (issue 17) is whether the DiT learns DiffIK's map at the reference's
# sample count. No regressor did across the full space on 2 cores (`control_ceiling_21m.md`, in git
# at 4fd8d8f; `control_ceiling_film_heldout.md`); within one structure a joints-anchored, design-modulated
# one did (52 %, `control_ceiling_nominal21m.md`). The DiT's run on that structure (without
# the last command: given it, the DiT feeds its own commands back and falls in closed loop,
# 11.8 % against 21.9 % at 256,000 windows, docs/experiments.md):
#   TRAIN_ARGS="--task control --size mini --batch-size 1024 --config online.space=viperx-nominal
#     --config online.designs=256 --config online.motions=4 --config online.refresh_every=20
#     --config future_states=false --config anchor_control=joints --config control_target_offset=2
#     --config prediction=x0" bash benchmarks/gpu_call.sh run
# and score the EMA weights that come back on the CPU with `python benchmarks/dit_control.py
# r1=$OUT/viperx_mini_online_ema.pt` (tt's controller: mean command, 7 queries averaged per
# command; 31.9 % of the oracle at 256,000 windows on 2 CPU cores, `dit_control_r1_ensemble.md`).
TRAIN_ARGS=${TRAIN_ARGS:---task both --size mini --batch-size 256 --config online.designs=256 --config online.motions=4 --config online.refresh_every=50}
mkdir -p "$OUT" "$STAGE"
export PYTHONUNBUFFERED=1

if [ -d .whl ]; then cp .whl/* "$STAGE"/ 2>/dev/null || true; fi
if [ "${1:-run}" = stage ]; then ls -la "$STAGE"; exit 0; fi

PY=python3
if ! $PY -c "import warp, mujoco, mujoco_warp, newton, mink, zarr, cma" 2>/dev/null; then
  for first in "$STAGE"/*.whl.part-00; do
    [ -e "$first" ] || continue
    cat "${first%.part-00}".part-* > "${first%.part-00}" && rm -f "${first%.part-00}".part-*
  done
  ls "$STAGE"/*.whl >/dev/null  # fails loudly when nothing was carried
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$STAGE"/*.whl
  export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
$PY -m pip install -q --no-deps --no-build-isolation -e . 2>&1 | tail -2
$PY - <<'PY'
import torch, warp as wp
import tt
wp.init()
print("torch", torch.__version__, "cuda", torch.cuda.is_available(), "| warp", wp.__version__, "cuda", wp.is_cuda_available())
assert torch.cuda.is_available() and wp.is_cuda_available(), "no CUDA device for torch or Warp"
PY
nvidia-smi --query-gpu=name,memory.total,driver_version,utilization.gpu --format=csv || true

# 1. The benchmark (budgets its own sections; 8 minutes at most).
timeout 520 $PY benchmarks/gpu.py --device cuda --out "$OUT/gpu.md" 2>&1 | tee "$OUT/gpu.log" | grep -v '^RESULT' || true

# 2. Online training on the GPU, stopped at TRAIN_SECONDS; checkpoints every 100 steps.
RUN=/tmp/tt_run_online
# shellcheck disable=SC2086  # TRAIN_ARGS is a list of flags
timeout "$TRAIN_SECONDS" tt train --online --device cuda $TRAIN_ARGS --steps 100000 --config checkpoint_every=100 \
  --out "$RUN" > "$OUT/train.log" 2>&1 || echo "training stopped at ${TRAIN_SECONDS} s (expected)" >> "$OUT/train.log"
tail -c 4000 "$OUT/train.log" | tr '\r' '\n' | tail -5

# 3. The EMA weights of the last checkpoint, without the optimizer state (loadable by load_model).
$PY - "$RUN" "$OUT" <<'PY'
import shutil, sys
from pathlib import Path
import torch
from tt.dit.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from tt.dit.ema import EMA
from tt.dit.model import RoboDiT

run, out = Path(sys.argv[1]), Path(sys.argv[2])
last = latest_checkpoint(run)
if last is None:
    sys.exit(f"no checkpoint in {run}: training did not reach checkpoint_every")
state = load_checkpoint(last)
model = RoboDiT.from_description(state["model"])
model.load_state_dict(state["state_dict"])
ema = EMA(model)
ema.load_state_dict(state["ema"])
ema.copy_to(model)
slim = {k: state[k] for k in ("schema_version", "model", "ema", "normalizer", "train_config", "step", "losses")}
path = save_checkpoint(out / "viperx_mini_online_ema.pt", {**slim, "state_dict": model.state_dict()})
size = path.stat().st_size
print(f"{path}: step {state['step']}, {size / 2**20:.1f} MiB")
assert size <= 16 * 2**20, "over the 16 MiB a file may have to come back"
if (run / "loss.csv").exists():
    shutil.copy(run / "loss.csv", out / "loss.csv")
PY
ls -la "$OUT"
