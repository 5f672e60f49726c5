"""One brax spring substep's VJP, piece by piece (session 28).

    python results/substep/scripts/step_vjp_parts.py TASK [--batch 32]

Forward and VJP (forward + backward, cotangent of ones) of each function brax's spring
pipeline step calls, vmapped over B envs and jitted alone, on states 10 control steps in
(contacts active): microseconds per call (min over 3 rounds of 100 calls) and VJP / forward.
README ILD speed, session 28: no piece dominates and none is far past 3x.
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
from brax import actuator, com, kinematics
from brax.spring import collisions, integrator, joints

from methods.ild.benchmark import vjp_of_ones
from tasks import make_task
from timing import best_seconds


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("task")
    p.add_argument("--batch", type=int, default=32)
    a = p.parse_args(argv)
    task = make_task(a.task)
    env = task.env.unwrapped
    if task.spec.backend != "spring":
        p.error(f"{a.task} runs brax's {task.spec.backend!r} backend; this times 'spring'")
    sys_ = env.sys
    step = jax.jit(jax.vmap(env.step))
    s = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), a.batch))
    act = jnp.full((a.batch, task.action_size), 0.3)
    for _ in range(10):
        s = step(s, act)
    ps = s.pipeline_state
    parts = {
        "inv_inertia": lambda p, u: com.inv_inertia(sys_, p.x),
        "actuator.to_tau": lambda p, u: actuator.to_tau(sys_, u, p.q, p.qd),
        "joints.resolve": lambda p, u: joints.resolve(sys_, p, actuator.to_tau(sys_, u, p.q,
                                                                              p.qd)),
        "collisions.resolve": lambda p, u: collisions.resolve(sys_, p),
        "integrator.integrate": lambda p, u: integrator.integrate(sys_, p.x_i, p.xd_i,
                                                                  p.xd_i * 0.01),
        "com.to_world": lambda p, u: com.to_world(sys_, p.x_i, p.xd_i),
        "kinematics.world_to_joint": lambda p, u: kinematics.world_to_joint(sys_, p.x, p.xd),
        "kinematics.inverse": lambda p, u: kinematics.inverse(sys_, p.j, p.jd),
        "one whole substep": lambda p, u: env._pipeline.step(sys_, p, u),
    }
    for name, fn in parts.items():
        vf = jax.vmap(fn)
        fwd = best_seconds(jax.jit(vf), ps, act, calls=100)
        back = best_seconds(jax.jit(vjp_of_ones(vf)), ps, act, calls=100)
        print(f"{name:26s} forward {fwd * 1e6:8.1f} us   vjp {back * 1e6:8.1f} us   "
              f"vjp / forward {back / fwd:5.2f}", flush=True)


if __name__ == "__main__":
    main()
