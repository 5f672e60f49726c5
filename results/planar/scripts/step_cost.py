"""What one control step costs, forward and as a VJP, through brax's step, through the step
ILD trains with, and through its planar form (`tasks.planar.control_step` for a positional
scene, session 66; `tasks.planar_spring.control_step` for a spring one, session 67).

    python results/planar/scripts/step_cost.py [--task inverted_pendulum] [--batch 32]
        [--calls 200] [--rounds 5]

Times, jitted, B envs 10 steps after reset (the same state for every row), microseconds
per call (the median over `--rounds` rounds of `--calls` calls, the rows interleaved round
by round):
- brax_forward: brax's `pipeline_step` as shipped;
- trained_forward: the step ILD's training rollouts run without `planar_adjoint` (the
  task's config otherwise: `lean_substeps`, `positional_joints` or `hand_adjoint` and its
  pieces, substep remat), which is also the forward `planar_adjoint` keeps;
- planar_forward: `control_step` (reacher's without its gravity along its hinges, as
  `planar_normal_gravity` differentiates it, session 72);
- brax_vjp, trained_vjp: the step's value and its VJP in the whole state and the action,
  for a cotangent equal to the output (XLA's reverse mode; trained_vjp with the config's
  hand-written VJPs and rematerialized substeps);
- planar_vjp: the same for `control_step` in the centre-of-mass frames and the action;
- links_forward, links_vjp (spring tasks): the same for `tasks.planar_links.control_step`,
  the planar spring step with every link at once (session 70).
Prints each row and the VJP / forward ratios.
"""
from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp

import tasks.planar as planar
from tasks import make_task


def rows(task_name: str, batch: int):
    """{row: (jitted function, args)} on `batch` envs 10 steps after reset."""

    from methods.ild.benchmark import task_config
    from methods.ild.train import rollout_physics
    task = make_task(task_name)
    env = task.env
    inner = env.unwrapped
    s = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))
    act = 0.5 * jnp.sin(jnp.arange(batch * inner.action_size, dtype=jnp.float32)
                        ).reshape(batch, inner.action_size)
    step = jax.jit(jax.vmap(env.step))
    for _ in range(10):
        s = step(s, act)
    ps = s.pipeline_state
    n = inner._n_frames
    links_fwd = None
    if task.spec.backend == "spring":
        import tasks.planar_links as planar_links
        import tasks.planar_spring as planar_spring
        sc = planar_spring.spring_scene(inner.sys)
        planar_fwd = jax.vmap(lambda xi, xdi, a: planar_spring.control_step(
            sc, inner.sys, xi, xdi, a, n))
        ls = planar_links.link_scene(sc)
        links_fwd = jax.vmap(lambda xi, xdi, a: planar_links.control_step(
            ls, inner.sys, xi, xdi, a, n))
    else:
        # reacher's gravity along its hinges left out, as planar_normal_gravity does
        # (inverted_pendulum's, in its plane, is kept either way)
        sc = planar.planar_scene(inner.sys, drop_normal_gravity=True)
        planar_fwd = jax.vmap(lambda xi, xdi, a: planar.control_step(sc, xi, xdi, a, n))
    cfg = task_config(task_name, batch, {"planar_adjoint": False})
    trained_fwd = jax.vmap(rollout_physics(task, cfg).env.unwrapped.pipeline_step)
    brax_fwd = jax.vmap(inner.pipeline_step)

    def vjp(f):
        def run(*args):
            out, pull = jax.vjp(f, *args)
            return out, pull(out)
        return jax.jit(run)

    table = {"brax_forward": (jax.jit(brax_fwd), (ps, act)),
             "trained_forward": (jax.jit(trained_fwd), (ps, act)),
             "planar_forward": (jax.jit(planar_fwd), (ps.x_i, ps.xd_i, act)),
             "brax_vjp": (vjp(brax_fwd), (ps, act)),
             "trained_vjp": (vjp(trained_fwd), (ps, act)),
             "planar_vjp": (vjp(planar_fwd), (ps.x_i, ps.xd_i, act))}
    if links_fwd is not None:
        table["links_forward"] = (jax.jit(links_fwd), (ps.x_i, ps.xd_i, act))
        table["links_vjp"] = (vjp(links_fwd), (ps.x_i, ps.xd_i, act))
    return table


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="inverted_pendulum")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--calls", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args(argv)
    table = rows(a.task, a.batch)
    for f, args in table.values():
        jax.block_until_ready(f(*args))
    times = {name: [] for name in table}
    for _ in range(a.rounds):
        for name, (f, args) in table.items():
            t0 = time.perf_counter()
            for _ in range(a.calls):
                out = f(*args)
            jax.block_until_ready(out)
            times[name].append((time.perf_counter() - t0) / a.calls * 1e6)
    med = {name: statistics.median(v) for name, v in times.items()}
    for name, us in med.items():
        print(f"{a.task} B={a.batch} {name}: {us:.1f} us per call "
              f"(rounds {min(times[name]):.1f}-{max(times[name]):.1f})")
    forms = [k for k in ("planar", "links") if f"{k}_vjp" in med]
    for kind in ("brax", "trained", *forms):
        print(f"{kind}: vjp / forward {med[f'{kind}_vjp'] / med[f'{kind}_forward']:.2f}x")
    for form in forms:
        for kind in ("brax", "trained", "planar")[:2 + (form == "links")]:
            print(f"{form} / {kind}: forward "
                  f"{med[f'{form}_forward'] / med[f'{kind}_forward']:.3f}x, vjp "
                  f"{med[f'{form}_vjp'] / med[f'{kind}_vjp']:.3f}x")
    return med


if __name__ == "__main__":
    main()
