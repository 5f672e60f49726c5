#!/bin/bash
# ILD's update against brax's APG and a forward rollout at the paper's batch on one GPU: one
# accelerator call, run from the repo root on the device machine, whose image ships jax
# 0.11.2 with CUDA 13, flax, optax, pandas, matplotlib and rich. The wheels it lacks travel
# in the ignored .whl/ folder (carry .whl): brax 0.14.2, mujoco 4.0.0 + mujoco-core 4.0.0
# (cp312), mujoco-mjx 3.17.0 (without its test_data/ folder, to keep the tree under 64 MiB),
# trimesh 5.2.0, ml_collections 1.1.0, jaxopt 0.8.5, tensorboardX 2.6.5
# (gpu_table_recipe.sh says how they were downloaded).
#
#   T=300 B=360 R=3 TASKS="hopper ant" bash benchmarks/gpu_speed_recipe.sh
#
# Per task two processes: `python -m benchmarks.ild_speed --rows forward,ild,ild_plain,chamfer
# --no-apg` and `--rows apg`, all on the one GPU, holding one file lock (`--time-lock`)
# exclusively around every timed section. Phase 1 starts the ILD processes together: they
# compile side by side and are timed one at a time, and nothing else runs on the GPU. Phase
# 2 starts the APG processes, APG_GROUP (default 2) at a time: each holds the lock shared
# over its first two epochs (brax compiles and runs them in one call) and exclusively over
# the timed third, so no timed section shares the GPU with another process's work (more APG
# processes at once compile for so long that their timed epochs may not start within a
# call). T bounds each process (seconds); the rows each process finished are in its CSV and
# log, re-packed into $OUT/speed_logs.tgz every 10 s, so a call cut off at its limit still
# brings back every row it finished. /tmp/speed outlives a call on a warm machine.
#
# Variables:
#   ILD_ROWS          the ILD processes' rows (default forward,ild,ild_plain,chamfer);
#                     ild_task times each task's update as it trains (its task overrides)
#   ILD_TASKS, APG_TASKS   the tasks of each phase (default TASKS; `none` skips a phase)
#   TOGETHER=1        start the APG processes with the ILD ones (one phase)
#   ALONE=1           start each ILD process after the one before ends (nothing compiles
#                     beside a timed section; slower)
#   DOTS_TASKS        add forward_dots,ild_substep_dots and an apg_dots process (small dots)
#   CLOSED_FORM_TASKS add ild_closed_form and an apg_closed_form process (acrobot)
#   LEAN_TASKS        add forward_lean,ild_lean and an apg_lean process (lean substeps)
#   ILD_BATCHES       each ILD task once per batch (default B), tagged ild_<task>_b<batch>
#   ILD_SETS          entries TASK:FIELD=VALUE[+FIELD=VALUE...]: one more ILD process timing
#                     ild_task with those fields on top, e.g. "ant:hand_adjoint=true"
# Example (every task's update as it trains, at B = 32 and 360, no APG):
#   T=420 B=360 APG_TASKS=none ILD_TASKS="ant humanoid hopper walker2d reacher acrobot
#     swimmer inverted_pendulum" ILD_ROWS=forward,ild_task ILD_BATCHES="32 360"
# On a GPU ant and humanoid train with hand_adjoint off (their GPU physics plans): their
# ild_task row there is XLA's reverse mode; ILD_SETS="ant:hand_adjoint=true" times the
# hand-written VJPs. XLA's GPU autotuner may pick other kernels for the same program when
# many processes compile beside it; ALONE=1 avoids that.
T=${T:-300} B=${B:-360} R=${R:-3}
TASKS=${TASKS:-"hopper ant walker2d humanoid reacher acrobot swimmer"}
ILD_ROWS=${ILD_ROWS:-forward,ild,ild_plain,chamfer} DOTS_TASKS=${DOTS_TASKS:-}
CLOSED_FORM_TASKS=${CLOSED_FORM_TASKS:-} LEAN_TASKS=${LEAN_TASKS:-}
ILD_TASKS=${ILD_TASKS:-$TASKS} APG_TASKS=${APG_TASKS:-$TASKS} APG_GROUP=${APG_GROUP:-2}
ILD_BATCHES=${ILD_BATCHES:-$B}
[ "$ILD_TASKS" = none ] && ILD_TASKS=
[ "$APG_TASKS" = none ] && APG_TASKS=
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
mkdir -p /tmp/speed
nvidia-smi --query-gpu=name,driver_version,memory.total,utilization.gpu --format=csv \
    > /tmp/speed/machine.txt
python3 -c "import jax, brax; print('jax', jax.__version__, jax.devices(), 'brax', \
brax.__version__)" >> /tmp/speed/machine.txt 2>&1 || { cat /tmp/speed/machine.txt; exit 1; }
cat /tmp/speed/machine.txt
bm() { tag=$1; shift; timeout $T python3 -m benchmarks.ild_speed --batch ${BB:-$B} \
    --repeats $R --chunk 1 --time-lock /tmp/speed/lock --out /tmp/speed/$tag.csv "$@" \
    > /tmp/speed/$tag.log 2>&1; echo "$tag exit $?"; }
pack() { [ -n "$OUT" ] && tar czf $OUT/.speed_logs.tgz -C /tmp speed \
    && mv $OUT/.speed_logs.tgz $OUT/speed_logs.tgz; }
(while true; do sleep 10; nvidia-smi --query-gpu=utilization.gpu,memory.used \
    --format=csv,noheader >> /tmp/speed/smi.log 2>&1; pack; done) > /dev/null 2>&1 &
watcher=$!
pids=() group=()
for phase in ild apg; do
  [ -z "$TOGETHER" ] && pids=()
  echo "phase $phase starts $(date +%T)"
  tasks=$ILD_TASKS; [ $phase = apg ] && tasks=$APG_TASKS
  for t in $tasks; do
    dots=no; [[ " $DOTS_TASKS " == *" $t "* ]] && dots=yes
    cf=no; [[ " $CLOSED_FORM_TASKS " == *" $t "* ]] && cf=yes
    lean=no; [[ " $LEAN_TASKS " == *" $t "* ]] && lean=yes
    if [ $phase = ild ]; then
      rows=$ILD_ROWS; [ $dots = yes ] && rows=$rows,forward_dots,ild_substep_dots
      [ $cf = yes ] && rows=$rows,ild_closed_form
      [ $lean = yes ] && rows=$rows,forward_lean,ild_lean
      for b in $ILD_BATCHES; do  # BB=b for this call alone (APG's processes run at B)
        tag=ild_$t; [ "$ILD_BATCHES" != "$B" ] && tag=ild_${t}_b$b
        BB=$b bm $tag --task $t --rows $rows --no-apg & pids+=($!)
        [ -n "$ALONE" ] && wait $!
      done
    else
      bm apg_$t --task $t --rows apg & pids+=($!) group+=($!)
      [ $dots = yes ] && { bm apg_dots_$t --task $t --rows apg_dots & pids+=($!) group+=($!); }
      [ $cf = yes ] && { bm apg_cf_$t --task $t --rows apg_closed_form & pids+=($!)
                         group+=($!); }
      [ $lean = yes ] && { bm apg_lean_$t --task $t --rows apg_lean & pids+=($!)
                           group+=($!); }
      # APG_GROUP APG processes at a time (a DOTS_TASKS, CLOSED_FORM_TASKS or LEAN_TASKS
      # pair or triple may make it one or two more): each timed epoch waits for every
      # warm-up running beside it
      [ ${#group[@]} -ge $APG_GROUP ] && { wait "${group[@]}"; group=(); }
    fi
  done
  i=0
  for e in $([ $phase = ild ] && echo $ILD_SETS); do  # TASK:FIELD=VALUE[+FIELD=VALUE...]
    sets=(); for f in $(echo ${e#*:} | tr + ' '); do sets+=(--set $f); done
    i=$((i+1)); bm ild_${e%%:*}_set$i --task ${e%%:*} --rows ild_task "${sets[@]}" --no-apg &
    pids+=($!); [ -n "$ALONE" ] && wait $!
  done
  [ -n "$TOGETHER" ] && [ $phase = ild ] && continue  # one phase: all processes at once
  [ ${#pids[@]} -gt 0 ] && wait "${pids[@]}"  # a bare wait would wait for the watcher
  echo "phase $phase ends $(date +%T)"
done
kill $watcher
grep -h "^{'task'" /tmp/speed/*.log
pack
