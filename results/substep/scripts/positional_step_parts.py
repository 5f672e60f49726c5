"""Session 64: one positional substep (`tasks.positional_joints.step(hand=True)`, what ILD's
`positional_joints` runs) piece by piece, vmapped over B envs and jitted alone on states
10 control steps in: microseconds forward and as a VJP (forward + backward, cotangent of
ones), and their ratio, as `results/substep/scripts/step_vjp_parts.py` times the spring
substep's pieces.

    python results/substep/scripts/positional_step_parts.py TASK [--batch 32] [--ops]

--ops: instead of timing, count each piece's operations in XLA's optimized HLO (forward
and VJP, `loop_ops.loops`' count: what the CPU runtime executes one by one), the measure
an update's time at B = 32 follows (results/JOURNAL.md, session 49).

Which of the pieces still in XLA's reverse mode (the joints' update, the position
corrections, the velocity projection, the actuators, the inverse kinematics) hold the
substep's VJP up.
"""
import argparse

import jax
from brax import actuator, kinematics
from brax.positional import integrator

import tasks.positional_joints as P
import tasks.spring_adjoint as sa
from bench.runner import cpu_model
from loop_ops import loops, ops_per_call
from methods.ild.benchmark import vjp_of_ones
from tasks import make_task
from timing import print_forward_and_vjp, states_in


def pieces(sys_, rows) -> dict:
    """The substep's pieces, each (pipeline_state, act) -> output, in the step's order."""
    return {
        "actuator.to_tau": lambda p, u: actuator.to_tau(sys_, u, p.q, p.qd),
        "acceleration_update (hand)": lambda p, u: P.acceleration_update(
            sys_, p, actuator.to_tau(sys_, u, p.q, p.qd), True),
        "integrate_xdd (hand)": lambda p, u: P.integrate_xdd(sys_, p.x_i, p.xd_i,
                                                             p.xd_i * 0.01),
        "to_world (hand)": lambda p, u: sa.to_world(sys_, p.x_i, p.xd_i),
        "world_to_joint (hand)": lambda p, u: sa.world_to_joint(sys_, p.x, p.xd),
        "inv_inertia (hand)": lambda p, u: sa.inv_inertia(sys_, p.x),
        "joint_update": lambda p, u: P.joint_update(p.j, rows),
        "world_to_joint + joint_update": lambda p, u: P.joint_update(
            sa.world_to_joint(sys_, p.x, p.xd)[0], rows),
        "position_update (hand)": lambda p, u: P.position_update(sys_, p, rows, True),
        "project_xd": lambda p, u: integrator.project_xd(sys_, p.x_i, p.x_i),
        "kinematics.inverse": lambda p, u: kinematics.inverse(sys_, p.j, p.jd),
        "one whole substep (hand)": lambda p, u: P.step(sys_, p, u, rows=rows, hand=True),
    }


def op_counts(parts: dict, ps, act) -> dict:
    """{name: (forward operations, VJP operations)} of each piece vmapped and jitted alone,
    counted as `loop_ops.loops` counts (the VJP: forward and backward, cotangent of
    ones)."""
    out = {}
    for name, f in parts.items():
        vf = jax.vmap(f)
        out[name] = tuple(ops_per_call(loops(jax.jit(g).lower(ps, act).compile().as_text()))
                          for g in (vf, vjp_of_ones(vf)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("task")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--ops", action="store_true")
    a = ap.parse_args(argv)
    task = make_task(a.task)
    sys_ = task.env.unwrapped.sys
    rows = P.joint_rows(sys_)
    ps, act = states_in(task, a.batch)
    parts = pieces(sys_, rows)
    print(f"{a.task}, B = {a.batch}, cpu {cpu_model()}")
    if not a.ops:
        print_forward_and_vjp(parts, ps, act)
        return
    for name, (fwd, vjp) in op_counts(parts, ps, act).items():
        print(f"{name:34s} forward {fwd:5d} ops   vjp {vjp:5d} ops   vjp - forward "
              f"{vjp - fwd:5d}", flush=True)


if __name__ == "__main__":
    main()
