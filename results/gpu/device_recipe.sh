#!/bin/bash
# How results/gpu was made (session 14): one accelerator call per seed, run from the repo
# root on the device machine (one H100; its image ships jax 0.11.2 with CUDA 13, flax 0.12.10,
# optax 0.2.8, pandas, rich, tabulate). The wheels the image lacks travel in an ignored
# .whl/ folder: brax 0.14.2, mujoco 4.0.0 + mujoco-core 4.0.0, mujoco-mjx 3.17.0, trimesh,
# ml_collections, jaxopt, tensorboardx (downloaded here with `pip download --no-deps
# --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 ...`).
# tasks/jax_compat.py restores the two names brax 0.14.2 needs on that JAX.
#
#   bash results/gpu/device_recipe.sh SEED 4m CELL_TIMEOUT_S     (SEED = 0, 1, 2)
#
# Per call: 8 ILD sweeps (one task each, --preset paper: B = 360) pinned to one CPU core
# each, plus 2 BC sweeps (4 tasks each, 2 cores each), all sharing the one GPU. Seed 0's
# humanoid cell ran past its call's limit and was re-run during seed 2's call as a 9th
# concurrent ILD sweep on 2 cores (its record says cpus 2).
export S=$1 B=$2 T=$3
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1 \
    ILDBENCH_JAX_CACHE=/tmp/jaxcache STORE=results/gpu/runs
mkdir -p /tmp/logs
sw() { tag=$1; shift; timeout $T python3 -c "from bench.cli import main; main()" sweep "$@" \
    --seeds 1 --seed-start $S --transfer --store $STORE --out /tmp/tables_$tag \
    > /tmp/logs/$tag.s$S.log 2>&1; }
export -f sw
pids=()
i=0
for t in hopper ant humanoid walker2d reacher swimmer inverted_pendulum acrobot; do
  taskset -c $i bash -c "sw ild_$t --methods ild --tasks $t --budget $B --preset paper" &
  pids+=($!); i=$((i+1))
done
taskset -c 8,9 bash -c "sw bc1 --methods bc --tasks hopper ant humanoid walker2d \
    --budget $B --preset paper" & pids+=($!)
taskset -c 10,11 bash -c "sw bc2 --methods bc --tasks reacher swimmer inverted_pendulum \
    acrobot --budget $B --preset paper" & pids+=($!)
(while true; do sleep 60; nvidia-smi --query-gpu=utilization.gpu,memory.used \
    --format=csv,noheader; done) > /tmp/logs/smi.s$S.log 2>&1 &
wait "${pids[@]}"
tar czf $OUT/runs_s$S.tgz $STORE
tar czf $OUT/logs_s$S.tgz /tmp/logs
