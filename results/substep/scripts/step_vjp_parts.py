"""One brax substep's VJP, piece by piece (spring: session 28; generalized: session 29).

    python results/substep/scripts/step_vjp_parts.py TASK [--batch 32]

Forward and VJP (forward + backward, cotangent of ones) of each function brax's spring or
generalized pipeline step calls, vmapped over B envs and jitted alone, on states 10 control
steps in (contacts active): microseconds per call (min over 3 rounds of 100 calls) and
VJP / forward, then one whole control step (all its substeps) the same way; on spring tasks
also the pieces `tasks.spring_adjoint` writes with a hand-written VJP (sessions 47-48).
results/JOURNAL.md: spring (session 28), no piece dominates and none is far past 3x;
generalized (session 29), where swimmer's and acrobot's step goes.
"""
from __future__ import annotations

import argparse

from brax import actuator, com, kinematics
from brax.generalized import constraint, dynamics, mass
from brax.generalized import integrator as g_integrator
from brax.spring import collisions, integrator, joints

from tasks import make_task
from timing import print_forward_and_vjp, states_in


def spring_parts(sys_) -> dict:
    """brax.spring.pipeline.step's functions, each (pipeline_state, act) -> output."""
    return {
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
    }


def hand_parts(sys_) -> dict:
    """The pieces `tasks.spring_adjoint` writes with a hand-written VJP (`hand_adjoint`,
    sessions 47-48), on the same inputs as their brax rows in `spring_parts`."""
    from tasks import spring_adjoint as sa
    return {
        "inv_inertia (hand VJP)": lambda p, u: sa.inv_inertia(sys_, p.x),
        "joints.resolve (hand VJP of its tail)": lambda p, u: sa.joints_resolve(
            sys_, p, actuator.to_tau(sys_, u, p.q, p.qd)),
        "collisions.resolve (hand VJP of its tail)": lambda p, u: sa.collisions_resolve(sys_,
                                                                                       p),
        "integrator.integrate (hand VJP)": lambda p, u: sa.integrate(sys_, p.x_i, p.xd_i,
                                                                     p.xd_i * 0.01),
        "com.to_world (hand VJP)": lambda p, u: sa.to_world(sys_, p.x_i, p.xd_i),
        "kinematics.world_to_joint (hand VJP)": lambda p, u: sa.world_to_joint(sys_, p.x,
                                                                               p.xd),
        "one whole substep (hand_adjoint)": lambda p, u: sa.step(sys_, p, u),
    }


def generalized_parts(sys_) -> dict:
    """brax.generalized.pipeline.step's functions in its order, each (pipeline_state, act) ->
    output; dynamics.forward split into its passive (springs, damping, fluid) and bias
    (inverse dynamics) terms, and the constraint solve timed alone."""
    return {
        "actuator.to_tau": lambda p, u: actuator.to_tau(sys_, u, p.q, p.qd),
        "dynamics._passive (fluid)": lambda p, u: dynamics._passive(sys_, p),
        "dynamics.inverse (bias)": lambda p, u: dynamics.inverse(sys_, p),
        "constraint.force (solver)": lambda p, u: constraint.force(sys_, p),
        "integrator.integrate": lambda p, u: g_integrator.integrate(sys_, p),
        "kinematics.forward": lambda p, u: kinematics.forward(sys_, p.q, p.qd),
        "dynamics.transform_com": lambda p, u: dynamics.transform_com(sys_, p),
        "mass.matrix_inv": lambda p, u: mass.matrix_inv(sys_, p, sys_.matrix_inv_iterations),
        "constraint.jacobian": lambda p, u: constraint.jacobian(sys_, p),
    }


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("task")
    p.add_argument("--batch", type=int, default=32)
    a = p.parse_args(argv)
    task = make_task(a.task)
    env = task.env.unwrapped
    if task.spec.backend not in ("spring", "generalized"):
        p.error(f"{a.task} runs brax's {task.spec.backend!r} backend; this times 'spring' "
                "and 'generalized'")
    sys_ = env.sys
    ps, act = states_in(task, a.batch)
    parts = spring_parts(sys_) if task.spec.backend == "spring" else generalized_parts(sys_)
    parts["one whole substep"] = lambda p, u: env._pipeline.step(sys_, p, u)
    if task.spec.backend == "spring":
        parts.update(hand_parts(sys_))
    parts[f"one control step ({env._n_frames} substeps)"] = env.pipeline_step
    print_forward_and_vjp(parts, ps, act)


if __name__ == "__main__":
    main()
