"""Where reacher's planar VJP goes (session 71, run with its patch applied; the patch is part
of tasks/planar.py since session 72).

One substep of `tasks.planar` (B = 32, 10 control steps after reset, one core), each piece's
value and VJP jitted alone, median ms over 5 rounds of 200 calls:

    python results/planar_reacher/substep_pieces_session71.py reacher
    python results/planar_reacher/substep_pieces_session71.py inverted_pendulum

reacher's arm (its two hinges; the target left out) against inverted_pendulum's cart and pole
(session 71, a first version of this script): position_update alone 0.22 / 0.12 ms,
integrate then position_update 8.0 / 0.45 ms, the whole substep 13.2 / 0.74 ms. This script
on reacher, core 1 idle: 0.37, 9.22 and 13.06 ms. Since session 72 `tasks.planar.substep`
passes integrate's frames through arrays (`_through_arrays`): the substep row runs that, the
integrate_then_position_update row still does not (its cost is the pathology that fixes).
"""
import dataclasses
import statistics
import sys
import time

import jax
import jax.numpy as jnp

import tasks.planar as P
from tasks import make_task

TASK = sys.argv[1]
B = 32
task = make_task(TASK)
env = task.env.unwrapped
sc = P.planar_scene(env.sys, True)
if TASK == "reacher":
    sc = dataclasses.replace(sc, links=sc.links[:2])   # the arm
L = len(sc.links)
s = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), B))
act = 0.5 * jnp.sin(jnp.arange(B * env.action_size, dtype=jnp.float32)).reshape(
    B, env.action_size)
step = jax.jit(jax.vmap(task.env.step))
for _ in range(10):
    s = step(s, act)
ps = s.pipeline_state
arrs = P._in_axes(sc.perm, (ps.x_i.pos[:, :L], ps.x_i.rot[:, :L], ps.xd_i.vel[:, :L],
                            ps.xd_i.ang[:, :L]))


def flat(tree):
    return jnp.stack([jnp.broadcast_to(jnp.asarray(a, jnp.float32), ())
                      for a in jax.tree.leaves(tree)])


def piece(name):
    def f(pos, rot, vel, ang, a):
        x_i, xd_i = P._tuples(pos, rot, vel, ang)
        tau = P.joint_torques(sc, a)
        x, xd = P.to_world(sc, x_i, xd_i)
        if name == "position_update":
            return flat(P.position_update(sc, x_i, x, xd))
        if name == "substep":
            return flat(P.substep(sc, x_i, xd_i, tau))
        jw = P.world_to_joint(sc, x, xd)
        forces = P.joint_forces(sc, tau, jw, x_i)
        xdd = [(P.vadd(sc.gravity, P.vscale(ln.mass_inv, fo[1])),
                P.matvec(P.inv_inertia(ln, xl[1]), fo[0]))
               for ln, fo, xl in zip(sc.links, forces, x)]
        x_i2, xd_i2 = P.integrate(sc, x_i, xd_i, xdd)
        x2, xd2 = P.to_world(sc, x_i2, xd_i2)
        return flat(P.position_update(sc, x_i2, x2, xd2))   # integrate_then_position_update
    return f


for name in ("position_update", "integrate_then_position_update", "substep"):
    f = jax.vmap(piece(name))

    def run(*a, f=f):
        out, pull = jax.vjp(f, *a)
        return pull(out)
    g = jax.jit(run)
    jax.block_until_ready(g(*arrs, act))
    ts = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(200):
            o = g(*arrs, act)
        jax.block_until_ready(o)
        ts.append((time.perf_counter() - t0) / 200 * 1e3)
    print(TASK, name, "value and VJP, ms", round(statistics.median(ts), 4))
