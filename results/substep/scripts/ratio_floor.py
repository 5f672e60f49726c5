"""Each part of ILD's update against its own forward (session 57): is update <= 3x forward
within reach of the parts the update is made of?

    python results/substep/scripts/ratio_floor.py TASK [--batch 32] [--rounds 6]
        [--repeats 8] [--out CSV]
    python results/substep/scripts/ratio_floor.py --summarize CSV [CSV ...]

Times, interleaved round by round in one process (every program compiled first; the first
round is a warm-up and is not kept), seconds per call of:
- forward, update: the benchmark's `forward` row (brax's step as shipped, ILD's policy and
  loss, no gradient) and ILD's update as TASK trains (`task_config`), as
  `methods.ild.paired` times them;
- policy_fwd, policy_grad: the rollout's policy alone over the episode (T steps of
  `sample_batch` on fixed observations), its value and its gradient in the parameters and
  the observations (the update needs both: the observations' cotangent goes on into the
  physics);
- physics_fwd, physics_train_fwd, physics_grad: the rollout's physics alone over the episode
  on fixed actions, per env normalized as the update normalizes it, with the truncation's
  stop_gradient, summed over its matched states: through brax's step as shipped, through
  the training physics (`rollout_physics`: substep remat, lean substeps, the hand-written
  adjoint, as the task's config sets), and its value and gradient in the actions through the
  training physics;
- loss_fwd, loss_grad: the loss on fixed matched states (B, T, D) against the goals, as the
  update computes it (`config.loss`, alive everywhere), its value and its gradient in the
  states.
The physics part differentiates the matched states, not the observations: the observations'
gradient into the policy is in the update's rest, with the optimizer and whatever policy and
physics cost together in one loop beyond their sum. Prints per part the median seconds over
rounds and the part's gradient / forward ratio (its range over rounds), the update against
the sum of its parts, and each part's seconds over 3x its forward. A reverse-mode gradient
through rematerialized physics runs the forward, the forward again next to its VJP, and the
VJP: <= 3x needs each part's VJP to cost no more than its forward.
"""
from __future__ import annotations

import argparse
import statistics

import jax
import jax.numpy as jnp

from bench.report import append_csv
from bench.runner import speed_settings
from methods.ild.benchmark import speed_setup, task_config
from methods.ild.config import ILDConfig
from methods.ild.paired import compiled_chunk, compiled_forward
from methods.ild.train import episode_loss, make_physics_step, rollout_physics, sample_actions
from tasks import make_task
from timing import interleaved_seconds

PARTS = ("forward", "update", "policy_fwd", "policy_grad", "physics_fwd",
         "physics_train_fwd", "physics_grad", "loss_fwd", "loss_grad")


def policy_programs(task, cfg: ILDConfig, setup):
    """(value, gradient) of the rollout's policy over the episode on fixed observations, as
    the update samples (`sample_actions`): value(params, obs) = sum over steps of
    <a_t, c_t>, gradient in (params, obs)."""
    policy, _, _, params, k = setup
    T, B = task.episode_length, cfg.num_envs
    obs = jax.random.normal(k[0], (T, B, task.obs_size))
    c = jax.random.normal(k[1], (T, B, task.action_size))
    keys = jax.random.split(k[2], T)

    def value(p, o):
        kernels_t = policy.kernels_t(p) if cfg.transposed_backward else None

        def body(total, xs):
            o_t, c_t, k_t = xs
            a = sample_actions(policy, p, o_t, k_t, kernels_t, cfg.swish_remat)
            return total + jnp.sum(a * c_t), None

        return jax.lax.scan(body, 0.0, (o, c, keys))[0]

    fwd = jax.jit(value)
    grad = jax.jit(jax.value_and_grad(value, argnums=(0, 1)))
    return (fwd, (params, obs)), (grad, (params, obs))


def physics_programs(task, cfg: ILDConfig, setup):
    """The rollout's physics alone over the episode on fixed actions (the update's
    `make_physics_step`, without the policy): value(actions) = sum over steps of
    <matched state, c_t>, through brax's step as shipped, through the training physics, and
    its gradient in the actions."""
    _, _, _, _, k = setup
    T, B = task.episode_length, cfg.num_envs
    acts = jnp.tanh(jax.random.normal(k[0], (T, B, task.action_size)))
    c = jax.random.normal(k[1], (T, B, task.state_size))
    init_keys = jax.random.split(k[2], B)

    def value_on(t):
        step = make_physics_step(t, cfg)

        def value(a_seq):
            def body(s, xs):
                i, a, c_t = xs
                s2, m, _ = step(s, a, i)
                return s2, jnp.sum(m * c_t)

            s0 = jax.vmap(t.env.reset)(init_keys)
            return jnp.sum(jax.lax.scan(body, s0, (jnp.arange(T), a_seq, c))[1])

        return value

    train = rollout_physics(task, cfg)
    return ((jax.jit(value_on(task)), (acts,)), (jax.jit(value_on(train)), (acts,)),
            (jax.jit(jax.value_and_grad(value_on(train))), (acts,)))


def loss_programs(task, cfg: ILDConfig, setup):
    """The update's loss alone (`episode_loss`) on fixed matched states: (value, value and
    gradient)."""
    _, goals, _, _, k = setup
    x = jax.random.normal(k[0], (cfg.num_envs, task.episode_length, task.state_size))
    alive = jnp.ones(x.shape[:2], bool)

    def value(x):
        return episode_loss(x, alive, goals, cfg)[0]

    return (jax.jit(value), (x,)), (jax.jit(jax.value_and_grad(value)), (x,))


def run(task_name: str, batch: int = 32, rounds: int = 6, repeats: int = 8) -> list[dict]:
    task = make_task(task_name)
    cfg = task_config(task_name, batch)
    setup = speed_setup(task, ILDConfig(num_envs=batch))
    chunk, state, n = compiled_chunk(task, cfg, setup)
    fwd, params = compiled_forward(task, ILDConfig(num_envs=batch), setup)
    pol_f, pol_g = policy_programs(task, cfg, setup)
    phy_f, phy_tf, phy_g = physics_programs(task, cfg, setup)
    loss_f, loss_g = loss_programs(task, cfg, setup)
    calls = {"forward": (fwd, (params,)), "update": (lambda s: chunk(s, n)[0], (state,)),
             "policy_fwd": pol_f, "policy_grad": pol_g, "physics_fwd": phy_f,
             "physics_train_fwd": phy_tf, "physics_grad": phy_g, "loss_fwd": loss_f,
             "loss_grad": loss_g}
    seconds = interleaved_seconds({p: calls[p] for p in PARTS}, rounds, repeats)
    settings = speed_settings()
    return [{"task": task_name, "batch": batch, "part": p, "round": r,
             "seconds": float(f"{s:.4g}"), **settings}
            for p in PARTS for r, s in enumerate(seconds[p])]


def summary_lines(rows: list[dict]) -> list[str]:
    by = {}
    for r in rows:
        by.setdefault(r["part"], []).append(r["seconds"])
    med = {p: statistics.median(s) for p, s in by.items()}

    def ratio(num, den):
        q = [a / b for a, b in zip(by[num], by[den])]
        return f"{statistics.median(q):.2f}x ({min(q):.2f}-{max(q):.2f}x)"

    task, batch = rows[0]["task"], rows[0]["batch"]
    parts = med["policy_grad"] + med["physics_grad"] + med["loss_grad"]
    fwd_parts = med["policy_fwd"] + med["physics_fwd"] + med["loss_fwd"]
    shares = ", ".join(f"{p.split('_')[0]} {med[p] / med['forward']:.0%}"
                       for p in ("policy_fwd", "physics_fwd", "loss_fwd"))
    rest, fwd_rest = med["update"] - parts, med["forward"] - fwd_parts
    over = {"policy": med["policy_grad"] - 3 * med["policy_fwd"],
            "physics": med["physics_grad"] - 3 * med["physics_fwd"],
            "loss": med["loss_grad"] - 3 * med["loss_fwd"], "rest": rest - 3 * fwd_rest}
    return [f"{task}, B = {batch}, {len(by['update'])} rounds; medians, s per call:",
            "  " + ", ".join(f"{p} {med[p]:.4f}" for p in PARTS),
            f"  update / forward {ratio('update', 'forward')}",
            f"  policy: grad / fwd {ratio('policy_grad', 'policy_fwd')}",
            f"  physics: grad / train fwd {ratio('physics_grad', 'physics_train_fwd')}, "
            f"grad / brax fwd {ratio('physics_grad', 'physics_fwd')}, "
            f"train fwd / brax fwd {ratio('physics_train_fwd', 'physics_fwd')}",
            f"  loss: grad / fwd {ratio('loss_grad', 'loss_fwd')}",
            f"  forward's parts: policy_fwd + physics_fwd + loss_fwd = {fwd_parts:.4f} s of "
            f"{med['forward']:.4f} ({shares}); the rest {fwd_rest:.4f} s",
            f"  update's parts: policy_grad + physics_grad + loss_grad = {parts:.4f} s of "
            f"{med['update']:.4f} ({parts / med['update']:.0%}); the rest (the optimizer, the "
            f"observations' gradient, policy and physics in one loop) {rest:.4f} s",
            "  seconds over 3x the part's forward (physics: brax's; rest: the forward's rest): "
            + ", ".join(f"{k} {v:+.4f}" for k, v in over.items())
            + f"; 3x the forward {3 * med['forward']:.4f}, the update {med['update']:.4f}"]


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("task", nargs="?")
    p.add_argument("--summarize", nargs="+", metavar="CSV",
                   help="print the summary of rows written earlier by --out, one per task "
                        "and batch, instead of timing")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--repeats", type=int, default=8)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    if a.summarize:
        import pandas as pd
        rows = pd.concat([pd.read_csv(f) for f in a.summarize]).to_dict("records")
        for key in dict.fromkeys((r["task"], r["batch"]) for r in rows):
            print("\n".join(summary_lines([r for r in rows
                                           if (r["task"], r["batch"]) == key])))
        return
    if not a.task:
        p.error("name a task to time, or --summarize CSV ...")
    rows = run(a.task, a.batch, a.rounds, a.repeats)
    for line in summary_lines(rows):
        print(line, flush=True)
    if a.out:
        append_csv(rows, a.out)


if __name__ == "__main__":
    from bench.malloc import reexec_with_hugepages
    reexec_with_hugepages()  # glibc's huge-page tunable, as `ildbench` and the benchmark run
    main()
