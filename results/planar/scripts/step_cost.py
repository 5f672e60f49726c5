"""What one control step costs, forward and as a VJP, through brax's positional step and
through its planar form (`tasks.planar.control_step`, session 66).

    python results/planar/scripts/step_cost.py [--task inverted_pendulum] [--batch 32]
        [--calls 200] [--rounds 5]

Times, jitted, B envs 10 steps after reset (the same state for every row), microseconds
per call (the median over `--rounds` rounds of `--calls` calls, the rows interleaved round
by round):
- brax_forward: brax's `pipeline_step` as shipped (the forward rollout's step);
- planar_forward: `control_step`;
- brax_vjp: the step's value and its VJP in the whole state and the action, XLA's reverse
  mode of brax's step, for a cotangent equal to the output;
- planar_vjp: the same for `control_step` in the centre-of-mass frames and the action.
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
    env = make_task(task_name).env
    inner = env.unwrapped
    s = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))
    act = 0.5 * jnp.sin(jnp.arange(batch * inner.action_size, dtype=jnp.float32)
                        ).reshape(batch, inner.action_size)
    step = jax.jit(jax.vmap(env.step))
    for _ in range(10):
        s = step(s, act)
    ps = s.pipeline_state
    sc, n = planar.planar_scene(inner.sys), inner._n_frames
    brax_fwd = jax.vmap(inner.pipeline_step)
    planar_fwd = jax.vmap(lambda xi, xdi, a: planar.control_step(sc, xi, xdi, a, n))

    def vjp(f):
        def run(*args):
            out, pull = jax.vjp(f, *args)
            return out, pull(out)
        return jax.jit(run)

    return {"brax_forward": (jax.jit(brax_fwd), (ps, act)),
            "planar_forward": (jax.jit(planar_fwd), (ps.x_i, ps.xd_i, act)),
            "brax_vjp": (vjp(brax_fwd), (ps, act)),
            "planar_vjp": (vjp(planar_fwd), (ps.x_i, ps.xd_i, act))}


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
    for kind in ("brax", "planar"):
        print(f"{kind}: vjp / forward {med[f'{kind}_vjp'] / med[f'{kind}_forward']:.2f}x")
    print(f"planar / brax: forward {med['planar_forward'] / med['brax_forward']:.3f}x, "
          f"vjp {med['planar_vjp'] / med['brax_vjp']:.3f}x")
    return med


if __name__ == "__main__":
    main()
