#!/bin/bash
# How results/gpu was made: one accelerator call per seed, run from the repo
# root on the device machine (one H100; its image ships jax 0.11.2 with CUDA 13, flax 0.12.10,
# optax 0.2.8, pandas, rich, tabulate). The wheels the image lacks travel in an ignored
# .whl/ folder: brax 0.14.2, mujoco 4.0.0 + mujoco-core 4.0.0, mujoco-mjx 3.17.0, trimesh,
# ml_collections, jaxopt, tensorboardx (downloaded here with `pip download --no-deps
# --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 ...`).
# tasks/jax_compat.py restores the two names brax 0.14.2 needs on that JAX.
#
#   bash benchmarks/gpu_table_recipe.sh SEED 4m CELL_TIMEOUT_S [METHOD]  (SEED = 0, 1, 2)
#
# Per call: 8 sweeps of METHOD (default ild; one task each, --preset paper: ILD's B = 360)
# pinned to one CPU core each, plus 2 side sweeps (2 cores each; default BC on 4 tasks each;
# SIDE1 / SIDE2 replace their arguments), all sharing the one GPU: 10 concurrent sweeps.
# A cell that runs past its call's limit re-runs in a later call (its record says how many
# cores it had). The references: METHOD=shac, and the sides run the planners, e.g.
#   SIDE1="--methods cem_mpc --tasks ant --seeds 3 --seed-start 0 --evals 1 --eval-episodes 8"
# (a side's --seeds / --seed-start come after the defaults and win; SIDE1=none skips it), and
# CELLS="0:hopper 1:ant ..." replaces the per-task list (one core per seed:task; default:
# SEED on the 8 tasks).
export S=$1 B=$2 T=$3 M=${4:-ild}
SIDE1=${SIDE1:-"--methods bc --tasks hopper ant humanoid walker2d"}
SIDE2=${SIDE2:-"--methods bc --tasks reacher swimmer inverted_pendulum acrobot"}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1 \
    ILDBENCH_JAX_CACHE=/tmp/jaxcache STORE=results/gpu/runs
mkdir -p /tmp/logs && touch /tmp/stamp
sw() { tag=$1; shift; timeout $T python3 -c "from bench.cli import main; main()" sweep \
    --seeds 1 --seed-start $S --transfer --store $STORE --out /tmp/tables_$tag "$@" \
    > /tmp/logs/$tag.log 2>&1; }
export -f sw
pids=()
i=0
CELLS=${CELLS:-$(for t in hopper ant humanoid walker2d reacher swimmer inverted_pendulum \
    acrobot; do echo -n "$S:$t "; done)}
for c in $CELLS; do
  s=${c%%:*} t=${c#*:}
  taskset -c $i bash -c "sw ${M}_$t.s$s --methods $M --tasks $t --budget $B --preset paper \
      --seed-start $s" &
  pids+=($!); i=$((i+1))
done
for side in SIDE1 SIDE2; do
  [ "${!side}" = none ] && continue
  taskset -c $i,$((i+1)) bash -c "sw $side.s$S ${!side} --budget $B --preset paper" & pids+=($!)
  i=$((i+2))
done
# pack: the run records written since the start and the logs, into $OUT under a temporary
# name and then renamed, so a call cut off at its limit still brings back a whole tarball of
# every record finished by the last pack (gpu_speed_recipe.sh does the same)
pack() { find $STORE -type f -newer /tmp/stamp | tar czf $OUT/.runs_s$S.tgz -T - \
    && mv $OUT/.runs_s$S.tgz $OUT/runs_s$S.tgz
    tar czf $OUT/.logs_s$S.tgz /tmp/logs && mv $OUT/.logs_s$S.tgz $OUT/logs_s$S.tgz; }
(while true; do sleep 30; nvidia-smi --query-gpu=utilization.gpu,memory.used \
    --format=csv,noheader >> /tmp/logs/smi.s$S.log 2>&1; pack; done) > /dev/null 2>&1 &
watcher=$!
wait "${pids[@]}"
kill $watcher
pack
