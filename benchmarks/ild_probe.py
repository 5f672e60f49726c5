"""How far does ILD's gradient reach? A probe of the loss around the BC warm start.

    python -m benchmarks.ild_probe --task hopper [--num-envs 10] [--positions-only] [--no-joint-limits]
        [--train-dynamics FAMILY[:MAGNITUDE][:fixed|fresh]]

From the BC warm start (the point every ILD run starts from) it takes one batch of rollouts
with fixed action noise and initial states, so the loss is a deterministic function of the
policy parameters, and prints:

- the analytic directional derivative along the loss gradient (full BPTT, no per-step
  normalization: the true gradient of this loss) next to central finite differences at
  eps = 1e-6 .. 1e-3 (in parameter-norm units). Where they agree the loss is smooth at that
  scale; where they disagree by orders of magnitude it jumps (contacts, sticky grasps);
- the loss after Adam's first step. Adam's bias-corrected first update is lr * sign(g) for
  every parameter (its size is lr * sqrt(#params), whatever the gradient's size), so this
  is exactly the first move an ILD run makes at that learning rate;
- the gradient ILD's update actually follows (the config's truncation and per-step
  normalization): its cosine with the true gradient, and the loss after Adam's first step
  along it. A negative cosine means the update climbs the loss it is meant to descend;
- what the per-step normalization does to that gradient: the norms of the per-env, per-step
  cotangents (the action's and the next state's) it sees, their largest and the fraction
  above 1, the ones it rescales (none on acrobot from the BC warm start, where `closed_form_adjoint`
  hands it another representation of the same cotangent).

`--no-joint-limits` runs the same probe on a copy of the task whose joint-range constraints
are removed (brax `sys.dof.limit = None`): where the loss turns smooth without them, the
roughness came from limits switching on and off between time steps (brax's generalized
backend solves them as constraints, like contacts).

`--train-dynamics` probes the loss in the changed dynamics a run trains in
(`bench.perturb.parse_dynamics`; cloth under the paper's protocol: `test_noise:1:fixed`).
"""
from __future__ import annotations

import argparse
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from methods.common.policy import ObsNorm, TanhGaussianPolicy, bc_pairs
from methods.ild.config import NORM_SCOPES, TASK_OVERRIDES, ILDConfig
from methods.ild.losses import observe_cotangent_norms
from methods.ild.train import StateNorm, bc_warm_start, make_rollout_loss
from tasks.core import without_joint_limits

EPS = (1e-6, 1e-5, 1e-4, 1e-3)
LRS = (1e-6, 1e-5, 1e-4, 1e-3)


def _norm(tree) -> float:
    return float(jnp.sqrt(sum(jnp.sum(x ** 2) for x in jax.tree_util.tree_leaves(tree))))


def probe(task, demo, config: ILDConfig, seed: int = 0, eps=EPS, lrs=LRS,
          positions_only: bool = False) -> dict:
    """Returns {'loss', 'grad_norm', 'params', 'other_keys', 'fd': {eps: value},
    'adam': {lr: loss after the first step}, 'cosine': cos(true gradient, the update's
    gradient), 'adam_used': {lr: loss after the first step along the update's gradient},
    'cotangents': {'count', 'max', 'clipped'} of the norms the per-step normalizer saw in
    the update's gradient (clipped: the fraction above 1, which it rescales to 1)}."""
    obs, actions = bc_pairs(task, demo)
    ds = jnp.asarray(demo.states[:, 1:])                                     # s_1..s_T
    norm = StateNorm.fit(ds, config.state_std_min)
    if positions_only:  # cloth: per particle (x, y, z, vx, vy, vz), then 8 gripper numbers
        if task.spec.name != "cloth":
            raise ValueError("--positions-only is for the cloth task's state layout")
        n = (norm.std.shape[0] - 8) // 6
        vel = np.concatenate([np.tile([False] * 3 + [True] * 3, n), np.zeros(8, bool)])
        # velocities weigh ~0 in the distance
        norm = norm.replace(std=jnp.where(jnp.asarray(vel), 1e6, norm.std))
    policy = TanhGaussianPolicy(task.obs_size, task.action_size, config.hidden)
    # the same key split as train(): the probe starts where a run with this seed starts
    init_key, bc_key, _, reset_key = jax.random.split(jax.random.PRNGKey(seed), 4)
    params = policy.init(init_key, ObsNorm.fit(obs, config.obs_std_min))
    if config.bc_updates > 0:
        params, _ = bc_warm_start(policy, params, obs, actions, config, bc_key)
    true_grad = dataclasses.replace(config, grad_normalization=False,
                                    truncation=task.episode_length)
    loss_fn = make_rollout_loss(task, policy, norm(ds), norm, true_grad)
    init_keys = jax.random.split(reset_key, config.num_envs)
    key = jax.random.PRNGKey(seed + 7)
    loss = jax.jit(lambda p, k: loss_fn(p, k, init_keys)[0])
    l0, g = jax.jit(jax.value_and_grad(lambda p: loss_fn(p, key, init_keys)[0]))(params)

    def moved(d, s):
        return {**params, "net": jax.tree.map(lambda a, b: a + s * b, params["net"], d)}

    gn = _norm(g["net"])
    u = jax.tree.map(lambda x: x / gn, g["net"])
    n_params = sum(x.size for x in jax.tree_util.tree_leaves(params["net"]))
    fd = {e: (float(loss(moved(u, e), key)) - float(loss(moved(u, -e), key))) / (2 * e)
          for e in eps}
    sign = jax.tree.map(jnp.sign, g["net"])
    adam = {lr: float(loss(moved(sign, -lr), key)) for lr in lrs}
    used_fn = make_rollout_loss(task, policy, norm(ds), norm, config)  # what ILD follows
    norms = []
    with observe_cotangent_norms(norms.append):
        gu = jax.jit(jax.grad(lambda p: used_fn(p, key, init_keys)[0]))(params)["net"]
        jax.effects_barrier()
    norms = np.concatenate([np.ravel(n) for n in norms]) if norms else np.zeros(0)
    dot = sum(jnp.sum(a * b) for a, b in zip(jax.tree_util.tree_leaves(g["net"]),
                                             jax.tree_util.tree_leaves(gu)))
    cosine = float(dot) / max(gn * _norm(gu), 1e-30)
    sign_u = jax.tree.map(jnp.sign, gu)
    adam_used = {lr: float(loss(moved(sign_u, -lr), key)) for lr in lrs}
    others = [float(loss(params, jax.random.PRNGKey(seed + 100 + i))) for i in range(4)]
    return {"loss": float(l0), "grad_norm": gn, "params": n_params, "other_keys": others,
            "fd": fd, "adam": adam, "cosine": cosine, "adam_used": adam_used,
            "cotangents": {"count": int(norms.size),
                           "max": float(norms.max()) if norms.size else 0.0,
                           "clipped": float((norms > 1.0).mean()) if norms.size else 0.0}}


def main(argv=None):
    from bench.runner import enable_compilation_cache
    from tasks import make_task
    from tasks.demo import load_demo
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", required=True)
    ap.add_argument("--num-envs", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--positions-only", action="store_true",
                    help="cloth: leave particle velocities out of the loss")
    ap.add_argument("--truncation", type=int, default=None,
                    help="the update's truncation window (default: ILD's for the task)")
    ap.add_argument("--no-joint-limits", action="store_true",
                    help="probe a copy of the task without its joint-range constraints")
    ap.add_argument("--train-dynamics", default=None,
                    help="probe in changed dynamics, as a run with --train-dynamics trains")
    ap.add_argument("--grad-norm-scope", choices=NORM_SCOPES, default=None,
                    help="the per-step normalization's scope (default: ILD's, 'env'; "
                         "'batch' is the original's one norm over all envs)")
    args = ap.parse_args(argv)
    enable_compilation_cache()
    task = make_task(args.task)
    demo = load_demo(task.spec.demo_path, task)
    if args.no_joint_limits:
        task = without_joint_limits(task)
    if args.train_dynamics is not None:
        from bench.access import TaskView
        from bench.api import Uses
        from bench.perturb import parse_dynamics
        task = TaskView(task, Uses(true_reward=True, sim_gradients=True), "ild_probe", None,
                        parse_dynamics(args.train_dynamics, task))
    config = dataclasses.replace(ILDConfig(num_envs=args.num_envs),
                                 **TASK_OVERRIDES.get(args.task, {}))
    if args.truncation is not None:
        config = dataclasses.replace(config, truncation=args.truncation)
    if args.grad_norm_scope is not None:
        config = dataclasses.replace(config, grad_norm_scope=args.grad_norm_scope)
    r = probe(task, demo, config, args.seed, positions_only=args.positions_only)
    print(f"{args.task}{' (positions only)' if args.positions_only else ''}"
          f"{' (no joint limits)' if args.no_joint_limits else ''}"
          f"{f' (training dynamics {args.train_dynamics})' if args.train_dynamics else ''}: B = "
          f"{config.num_envs}, {r['params']} parameters, from the BC warm start")
    print(f"loss {r['loss']:.4f} (4 other action-noise draws: "
          f"{', '.join(f'{x:.4f}' for x in r['other_keys'])})")
    print(f"directional derivative along the gradient: analytic {r['grad_norm']:.4g}")
    for e, v in r["fd"].items():
        print(f"  finite difference, eps {e:g}: {v:.4g} (ratio {v / r['grad_norm']:.3g})")
    print("loss after Adam's first step (lr * sign(g)):")
    for lr, v in r["adam"].items():
        print(f"  lr {lr:g} (step norm {lr * np.sqrt(r['params']):.3g}): {v:.4f} "
              f"({v / r['loss']:.2f}x)")
    print(f"the update's gradient (truncation {config.truncation}, per-step normalization "
          f"{'on' if config.grad_normalization else 'off'}): cosine with the true gradient "
          f"{r['cosine']:.3f}; loss after Adam's first step along it:")
    for lr, v in r["adam_used"].items():
        print(f"  lr {lr:g}: {v:.4f} ({v / r['loss']:.2f}x)")
    c = r["cotangents"]
    if c["count"]:
        per = "per env and step" if config.grad_norm_scope == "env" else "all envs, per step"
        print(f"per-step normalization: {c['count']} cotangents (action and next state, {per}"
              f"), largest norm {c['max']:.3g}, {100 * c['clipped']:.2f}% above 1 "
              "(rescaled to 1)")


if __name__ == "__main__":
    main()
