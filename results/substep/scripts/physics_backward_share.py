"""How much of ILD's update is brax's physics backward, and how cheap would a hand-written
adjoint have to be for the update to cost <= 3x a forward rollout? (session 46)

    python results/substep/scripts/physics_backward_share.py TASK [--batch 32] [--repeats 5]
        [--out CSV]

Times in one process, as `python -m methods.ild.benchmark` does (`_time`: compiled once,
then the mean over `--repeats` calls; with glibc's huge-page tunable, `bench.malloc`), B
envs, the config TASK trains with (`ild_task`):
- `forward`: the 128-step rollout and its Chamfer loss through brax's step as shipped (the
  benchmark's `forward`, the issue's yardstick), and `forward_trained` through the physics
  the update differentiates (lean substeps on the spring and positional tasks);
- `forward_no_physics`: the same rollout with the physics step replaced by a stand-in that
  costs next to nothing (the state passed on with the action added to the first entries
  of qd, so the policy still sees something that depends on its action);
- `update`: ILD's update as the task trains (`ild_task`);
- `update_free_backward`: the same update whose physics step runs forward as it trains
  but whose backward is free: a custom_vjp passing the output state's cotangent straight
  to the input state and the first entries of qd's cotangent to the action (nothing
  upstream is pruned: the policy's backward, the normalization's, the loss's and the
  optimizer's all run as in `update`).
From these: the physics' share of the forward P = forward_trained - forward_no_physics,
its backward's share of the update Q = update - update_free_backward, the backward's cost
in forwards Q / P, and the most a hand-written adjoint may cost, in physics forwards, for
the update to be 3x `forward`: (3 forward - update_free_backward) / P (a rematerializing
adjoint spends one of those on recomputing the forward).
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

from bench.malloc import reexec_with_hugepages
from bench.report import append_csv
from methods.ild.benchmark import _time, make_rollout_loss, speed_setup, task_config
from methods.ild.train import initial_state, make_update, rollout_physics
from tasks import make_task


def _qd_to_action(ct_qd, act_size: int):
    """The first `act_size` entries of qd's cotangent as the action's (zeros past qd)."""
    n = min(act_size, ct_qd.shape[-1])
    return jnp.zeros(ct_qd.shape[:-1] + (act_size,), ct_qd.dtype).at[..., :n].set(
        ct_qd[..., :n])


def with_free_backward(task):
    """`task` (a rollout_physics copy: its env has its own pipeline_step) whose physics step
    keeps its forward and gets the free backward described above."""
    inner = task.env.unwrapped
    step_fn = inner.pipeline_step
    act_size = task.action_size

    @jax.custom_vjp
    def step(ps, action):
        return step_fn(ps, action)

    def fwd(ps, action):
        return step(ps, action), None

    def bwd(_, ct):
        return ct, _qd_to_action(ct.qd, act_size)

    step.defvjp(fwd, bwd)
    inner.pipeline_step = step
    return task


def with_no_physics(task):
    """`task` whose physics step is the near-free stand-in described above."""
    inner = task.env.unwrapped
    act_size = task.action_size

    def step(ps, action):
        n = min(act_size, ps.qd.shape[-1])
        return ps.replace(qd=ps.qd.at[..., :n].add(0.01 * action[..., :n]))

    inner.pipeline_step = step
    return task


def main():
    reexec_with_hugepages()  # as the benchmark and `ildbench` run (bench.malloc)
    p = argparse.ArgumentParser()
    p.add_argument("task")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out")
    a = p.parse_args()
    task = make_task(a.task)
    cfg = task_config(a.task, a.batch)
    policy, goals, norm, params, k = speed_setup(task, cfg)
    init_keys = jax.random.split(k[2], a.batch)
    sec = {}

    def forward(name, physics):
        loss = make_rollout_loss(physics, policy, goals, norm, cfg)
        sec[name] = _time(lambda q: loss(q, k[3], init_keys)[0], (params,), a.repeats).seconds
        print(name, round(sec[name], 4), flush=True)

    def update(name, physics):
        upd, opt, _ = make_update(physics, policy, goals, norm, cfg, k[2])
        state = initial_state(params, opt, k[3], cfg)
        sec[name] = _time(lambda s: upd(s, None)[0], (state,), a.repeats).seconds
        print(name, round(sec[name], 4), flush=True)

    trained = rollout_physics(task, cfg)  # a fresh copy each: the with_* below rewrite theirs
    forward("forward", task)
    forward("forward_trained", trained)
    forward("forward_no_physics", with_no_physics(rollout_physics(task, cfg)))
    update("update", trained)
    update("update_free_backward", with_free_backward(rollout_physics(task, cfg)))
    P = sec["forward_trained"] - sec["forward_no_physics"]
    Q = sec["update"] - sec["update_free_backward"]
    row = {"task": a.task, "batch": a.batch, **{k_: round(v, 5) for k_, v in sec.items()},
           "update_over_forward": round(sec["update"] / sec["forward"], 3),
           "free_backward_update_over_forward": round(
               sec["update_free_backward"] / sec["forward"], 3),
           "physics_share_of_forward_trained": round(P / sec["forward_trained"], 3),
           "physics_backward_share_of_update": round(Q / sec["update"], 3),
           "physics_backward_over_physics_forward": round(Q / P, 3),
           "adjoint_budget_in_physics_forwards_for_3x": round(
               (3 * sec["forward"] - sec["update_free_backward"]) / P, 3)}
    print(row, flush=True)
    if a.out:
        append_csv([row], a.out)


if __name__ == "__main__":
    main()
