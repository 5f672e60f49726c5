#!/bin/bash
# ILD's update against brax's APG and a forward rollout at the paper's batch on one GPU
# (session 34): one accelerator call, run from the repo root on the device machine, whose
# image ships jax 0.11.2 with CUDA 13, flax, optax, pandas, matplotlib and rich. The wheels it
# lacks travel in the ignored .whl/ folder (carry .whl): brax 0.14.2, mujoco 4.0.0 +
# mujoco-core 4.0.0 (cp312), mujoco-mjx 3.17.0, trimesh 5.2.0, ml_collections 1.1.0,
# jaxopt 0.8.5, tensorboardX 2.6.5 (device_recipe.sh says how they were downloaded).
#
#   T=300 B=360 R=3 TASKS="hopper ant" bash results/gpu/speed_recipe.sh
#
# Per task two processes: `python -m methods.ild.benchmark --rows forward,ild,ild_plain,chamfer
# --no-apg` and `--rows apg`, all on the one GPU, holding one file lock (`--time-lock`)
# exclusively around every timed section. Phase 1 starts the ILD processes together: they
# compile side by side (16 CPU cores) and are timed one at a time, and nothing else runs on
# the GPU. Phase 2 starts the APG processes, APG_GROUP at a time: each holds the lock
# shared over its first two epochs (brax compiles and runs them in one call) and
# exclusively over the timed third, so no timed section shares the GPU with another
# process's work. T bounds each
# process (seconds); the rows each process finished are in its CSV and log, which come back
# in $OUT/speed_logs.tgz.
#
# Session 34 ran it twice on one H200 (results/gpu/speed_session34, results/JOURNAL.md): call 1
# started all 14 processes at once with no shared hold (APG's first epochs could share the GPU
# with a timed section), T=400, every row but acrobot's APG (brax's trainer lacked the JAX shim
# there; apg_epochs applies it since); call 2 started them at once with the shared hold and
# stalled (the GPU idle from 60 s to 240 s, every process at its T=355 limit).
#
# Session 37 (one H200, results/gpu/speed_session37): call 1 ran the two phases on all
# seven tasks with ILD_ROWS=forward,ild, T=265: the ILD phase finished in 106 s, and none of
# the 8 APG processes of phase 2 finished (GPU mostly idle, as in session 34's call 2). The
# lock does not deadlock (flock converts shared -> exclusive by dropping the shared hold
# first); each timed epoch waits for every other process's warm-up, which with 8 processes
# compiling at once did not end in time. Call 2 ran 2 APG processes (hopper, acrobot) beside
# swimmer's ILD process: both finished in 114 s (their epoch log: apg_epochs_call2.log).
# Hence APG_GROUP (default 2): APG processes start in groups of that size.
#
# Session 37 (ILD_ROWS, DOTS_TASKS): ILD_ROWS replaces the ILD processes' rows (default
# forward,ild,ild_plain,chamfer); each task in DOTS_TASKS adds forward_dots,ild_substep_dots
# to its ILD process and a second APG process with --rows apg_dots (brax's APG on the same
# small-dots physics), e.g.
#   T=270 TASKS="hopper acrobot swimmer" ILD_ROWS=forward,ild DOTS_TASKS=swimmer bash ...
# ILD_TASKS / APG_TASKS (default TASKS) pick the tasks of each phase. TOGETHER=1 starts
# the APG processes with the ILD ones (one phase; the lock still keeps every timed section
# alone on the GPU, but a timed section waits for every APG warm-up).
#
# Session 38 (CLOSED_FORM_TASKS, first run on a GPU in session 45): each task in it
# (acrobot, the one with a closed-form step) adds ild_closed_form to its ILD process and a
# second APG process with --rows apg_closed_form (brax's APG through the same closed-form
# backward), e.g.
#   T=270 TASKS=acrobot ILD_ROWS=forward,ild CLOSED_FORM_TASKS=acrobot bash ...
# Since session 39 acrobot trains through its closed form and swimmer with small dots by
# task override; the benchmark's ild_task row times each task's update as it trains
# (ILD_ROWS=forward,ild,ild_task), to set beside `apg` (brax as shipped) and, for the
# like-with-like ratio, apg_closed_form / apg_dots (CLOSED_FORM_TASKS / DOTS_TASKS).
#
# Session 40 (LEAN_TASKS, first run on a GPU in session 45): each task in it (spring and
# positional: hopper, walker2d, ant, humanoid, reacher) adds forward_lean,ild_lean to its
# ILD process and a second APG process with --rows apg_lean (brax's APG on the same lean
# substeps), e.g.
#   T=300 TASKS="hopper ant" ILD_ROWS=forward,ild LEAN_TASKS="hopper ant" bash ...
# Since session 41 those five and inverted_pendulum train with lean substeps by task
# override, so their ild_task row is the lean update (on the five, ild_lean's own config,
# timed once); with LEAN_TASKS it is also set beside apg_lean.
#
# Session 45 (one H200, results/gpu/speed_session45): one call, `T=300 APG_GROUP=4
# TASKS="acrobot swimmer hopper ant" ILD_ROWS=forward,ild,ild_task CLOSED_FORM_TASKS=acrobot
# DOTS_TASKS=swimmer LEAN_TASKS="hopper ant"`, timeout 570 s. The ILD phase took 161 s; the
# first APG group of four (acrobot's and swimmer's pairs) 166-232 s, since four of brax's
# APG warm-ups at once compile for 40-100 s each and every timed epoch waits for them; the
# second group (hopper's and ant's) was cut off by the call's limit before its first epoch,
# and the tarball at the end never ran (a second call fetched /tmp/speed from the warm
# machine). Hence: the watcher below re-packs $OUT/speed_logs.tgz every 10 s, so a call
# cut off at its limit still brings back every row it finished; and ILD_TASKS=none /
# APG_TASKS=none skip a phase. brax's APG on hopper and ant (lean or as shipped) compiles
# its first epoch in 100-116 s on that image even two at a time, so for those two, e.g.
#   T=280 ILD_TASKS=none APG_TASKS=hopper LEAN_TASKS=hopper bash ...   (one pair, ~250 s)
#
# Session 46 (one H200, results/gpu/speed_session46): three calls on one warm machine,
#   T=370 APG_GROUP=4 ILD_TASKS=none APG_TASKS="hopper ant" LEAN_TASKS="hopper ant" (281 s),
#   T=300 APG_TASKS=none ILD_TASKS="hopper ant walker2d humanoid reacher"
#     ILD_ROWS=forward,ild,ild_task LEAN_TASKS="<the same five>" (186 s),
#   T=300 APG_GROUP=4 ILD_TASKS=none APG_TASKS="walker2d reacher" LEAN_TASKS=<the same> (288 s):
# four APG processes at once reach their timed epoch in 180-196 s. /tmp/speed outlives a call
# on a warm machine, so the last call's tarball holds every call's logs.
#
# Since session 50 hopper, walker2d, ant and humanoid train with hand_adjoint (hand-written
# VJPs of brax's spring substep) by task override: their ild_task row is that update, and
# the ild_hand rows set it beside ild_xla, the same lean update through XLA's reverse mode
# (what they trained with before). Not yet run on a GPU; one call would be
#   T=300 APG_TASKS=none ILD_TASKS="hopper walker2d ant humanoid" ILD_ROWS=forward,ild_hand
#
# Session 56 (ILD_BATCHES): each ILD task runs once per batch in ILD_BATCHES (default B),
# one process each, tagged ild_<task>_b<batch> when there are several, e.g.
#   T=330 APG_TASKS=none ILD_TASKS="hopper walker2d ant humanoid"
#     ILD_ROWS=forward,forward_lean,ild_hand ILD_BATCHES="360 2048" bash ...
# ILD_SETS: each entry TASK:FIELD=VALUE[+FIELD=VALUE...] adds one ILD process timing the
# ild_task row with those fields on top (the benchmark's --set; named ild_task:FIELD=VALUE)
# at B, tagged ild_<task>_set<i>, e.g. ILD_SETS="ant:hinge_forces=false".
# Session 56 ran two calls (results/gpu/speed_session56, results/JOURNAL.md):
#   T=330 APG_TASKS=none ILD_TASKS="hopper walker2d ant humanoid"
#     ILD_ROWS=forward,forward_lean,ild_hand ILD_BATCHES="360 2048"        (296 s)
#   T=290 APG_TASKS=none ILD_TASKS="ant humanoid" ILD_ROWS=forward_lean,ild_hand
#     ILD_SETS="ant:hinge_forces=false humanoid:hinge_forces=false
#     humanoid:rotary_joints=false humanoid:hinge_forces=false+rotary_joints=false
#     ant:substep_remat=false humanoid:substep_remat=false hopper:substep_remat=false" (266 s)
# Ant's ild_hand / ild_xla flipped between the two calls (0.532 / 0.434 s, then 0.470 /
# 0.573 s) while its forward's working memory changed by 32 MiB between them (95.6 / 63.6
# MiB): the same program compiled to other kernels, likely XLA's GPU autotuner timing GEMM
# candidates while 8-9 processes compiled beside it. ALONE=1 starts each ILD process after
# the one before ends (nothing compiles beside a timed section or an autotuning compile;
# slower: every compile in series), the next check of ant and humanoid, e.g.
#   T=280 ALONE=1 APG_TASKS=none ILD_TASKS="ant humanoid" ILD_ROWS=forward_lean,ild_hand
# (about 6 minutes: session 56's compiles took 15-30 s per forward, 50-120 s per update).
# The tree that travels must stay under 64 MiB with .whl: session 56 carried mujoco_mjx's
# wheel without its test_data/ folder (7.3 -> 0.7 MB; its RECORD lines for it dropped too).
#
# Session 75 (one H200, results/gpu/speed_session75, column `call`): three calls, each
# processes' compiles side by side and every timed section alone under the lock:
#   T=420 B=360 APG_TASKS=none ILD_TASKS="ant humanoid hopper walker2d reacher acrobot
#     swimmer inverted_pendulum" ILD_ROWS=forward,ild_task ILD_BATCHES="32 360"
#     ILD_SETS="ant:hand_adjoint=false humanoid:hand_adjoint=false"        (18 processes, 284 s)
#   T=230 B=32 APG_TASKS=none ILD_TASKS=ant ILD_ROWS=forward,forward_lean,ild_task
#     ILD_SETS="ant:saved_residuals=false ant:hand_adjoint=false ant:hinge_forces=false
#     ant:substep_remat=false humanoid:hand_adjoint=false humanoid:rotary_joints=false" (139 s)
#   T=175 B=360 APG_TASKS=none ILD_TASKS=ant ILD_ROWS=forward,ild_task
#     ILD_SETS="ant:saved_residuals=false ant:hand_adjoint=false
#     humanoid:saved_residuals=false"                                       (4 processes, 116 s)
# The tree that travelled with .whl was 63.7 MB of the 64 MiB limit (mujoco_mjx's wheel
# without test_data/, as session 56's).
# Since session 75 ant and humanoid train on a GPU with hand_adjoint off (ILD's
# PLATFORM_OVERRIDES): their ild_task row there is XLA's reverse mode, and
# ILD_SETS="ant:hand_adjoint=true" times the hand-written VJPs.
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
bm() { tag=$1; shift; timeout $T python3 -m methods.ild.benchmark --batch ${BB:-$B} \
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
