"""`planar_adjoint` on the spring backend: brax's spring control step written over the plane
hopper and walker2d move in (`tasks.physics.planar_spring`), differentiated in place of the
step ILD trains with. The same values and derivative as that step, with contacts active, and clear
refusals where a scene leaves the plane."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax import com, contact, kinematics

import tasks.physics.planar as planar
import tasks.physics.planar_spring as planar_spring
from benchmarks.ild_speed import speed_setup, task_config
from methods.ild.train import make_rollout_loss
from tasks import make_task
from tasks.physics import Plan
from tasks.core import Task
from tasks.physics.transforms import planar_adjoint_refusal, with_planar_adjoint
from tests.test_hand_adjoint import _states
from tests.test_planar import assert_same_step, assert_same_vjp

F = planar._f32


def test_spring_scene_reads_hopper_and_walker2d():
    """hopper: a planar root (slides along x and z, rows 0 and 1; the hinge about y, row 2)
    under the world, three hinges below it, each limited (the foot's to +/-0.785 rad);
    gravity -9.81 along z in 0.002-s substeps; the foot capsule's two ends (half-length
    0.195, radius 0.06, friction 2) on the floor, the impulse reading flat entry 3 of brax's
    inverse inertias (link 0's row 1, column 0). walker2d: the same root, six hinges in two
    legs, and six contacts (torso, both feet), reading flat entries 0, 3 and 6."""
    sys = make_task("hopper").env.unwrapped.sys
    sc = planar_spring.spring_scene(sys)
    root, thigh, leg, foot = sc.links
    assert [ln.parent for ln in sc.links] == [-1, 0, 1, 2]
    assert root.root and not any(ln.root for ln in (thigh, leg, foot))
    assert root.dofs == (0, 1, 2) and foot.dofs == (5,)
    assert root.slides == ((0, (1.0, 0.0, 0.0)), (1, (0.0, 0.0, 1.0))) and root.turn == 2
    assert thigh.limit == (F(-2.61799), 0.0) and foot.limit == (F(-0.785398), F(0.785398))
    assert sc.gravity == (0.0, 0.0, F(-9.81)) and sc.dt == F(0.002)
    assert sc.actuators[0][:2] == (3, 200.0)
    c0, c1 = sc.contacts
    assert (c0.link, c1.link) == (3, 3) and (c0.half, c1.half) == (F(0.195), F(-0.195))
    assert c0.radius == F(0.06) and c0.friction == 2.0 and c0.flat == (0, 1, 0)
    assert c0.normal == (0.0, 0.0, 1.0)
    assert planar_spring.spring_refusal(sys) is None
    walker = planar_spring.spring_scene(make_task("walker2d").env.unwrapped.sys)
    assert [ln.parent for ln in walker.links] == [-1, 0, 1, 2, 0, 4, 5]
    assert [c.link for c in walker.contacts] == [0, 0, 3, 3, 6, 6]
    assert [c.flat for c in walker.contacts[::2]] == [(0, 0, 0), (0, 1, 0), (0, 2, 0)]
    assert [c.friction for c in walker.contacts] == [F(0.9)] * 4 + [F(1.9)] * 2


def test_spring_planar_adjoint_refuses_what_it_does_not_model():
    """ant and humanoid (free roots, joints that turn about other axes), hopper with gravity
    along y, with its thigh's hinge turned about x (its substep leaves the plane) or with
    a fluid: each refused by name. The config pairs planar_adjoint with hand_adjoint (the
    forward it keeps) but not with small_dots or closed_form_adjoint."""
    for name in ("ant", "humanoid"):
        with pytest.raises(ValueError, match=f"'{name}': it has a joint that is neither one "
                                             "dof nor a planar root; planar_adjoint"):
            with_planar_adjoint(make_task(name))
    hopper = make_task("hopper")
    assert planar_adjoint_refusal(hopper) is None
    sys = hopper.env.unwrapped.sys
    assert planar_spring.spring_refusal(sys.replace(gravity=jnp.array([0.0, -9.81, 0.0]))) == (
        "its gravity is not in the x-z plane")
    assert planar_spring.spring_refusal(sys.replace(enable_fluid=True)) == (
        "it has fluid forces")
    motion = sys.dof.motion.replace(ang=sys.dof.motion.ang.at[3].set(jnp.array([1.0, 0, 0])))
    why = planar_spring.spring_refusal(sys.replace(dof=sys.dof.replace(motion=motion)))
    assert why.startswith("a substep moves it out of the x-z plane ("), why
    Plan(planar_adjoint=True, hand_adjoint=True, hinge_forces=True, planar_root=True)
    for other in ("closed_form_adjoint", "small_dots"):
        with pytest.raises(ValueError, match=f"(?=.*planar_adjoint)(?=.*{other}).*False"):
            Plan(planar_adjoint=True, **{other: True})


def _consistent(sys, ps, x_i, xd_i):
    """`ps` with every frame, joint coordinate and the inverse inertia computed from `x_i`,
    `xd_i`, as brax's spring substep ends (the function of those frames `control_step`
    is)."""
    x, xd = com.to_world(sys, x_i, xd_i)
    j, jd, a_p, a_c = kinematics.world_to_joint(sys, x, xd)
    q, qd = kinematics.inverse(sys, j, jd)
    return ps.replace(x=x, xd=xd, x_i=x_i, xd_i=xd_i, j=j, jd=jd, a_p=a_p, a_c=a_c, q=q,
                      qd=qd, i_inv=com.inv_inertia(sys, x))


def _control_steps(name: str, form=None, without: str = "planar_adjoint", batch: int = 8):
    """(trained, ours, args, dist): one control step of `batch` envs of `name` 15 steps
    after reset (hopper's foot on the floor in half of them), as functions of (x_i, xd_i,
    action) returning `control_step`'s outputs: the step ILD trains with (its config
    without the field `without`: hand_adjoint's spring substep, lean substeps) with the
    state's other fields computed from x_i, xd_i, and the form `form(sys, n_frames)` returns
    for one env (the planar form where None), vmapped; `dist`, the contacts' distances."""
    task, ps, act = _states(name, batch=batch, steps=15)
    cfg = task_config(name, batch, {without: "false"})
    env = cfg.physics(task).env.unwrapped
    sys, n = env.sys, env._n_frames
    if form is None:
        sc = planar_spring.spring_scene(sys)
        form = lambda sys, n: (lambda xi, xdi, a: planar_spring.control_step(  # noqa: E731
            sc, sys, xi, xdi, a, n))
    ours = jax.vmap(form(sys, n))

    def trained(xi, xdi, a):
        step = lambda p_, xi_, xdi_, a_: env.pipeline_step(  # noqa: E731
            _consistent(sys, p_, xi_, xdi_), a_)
        # the masses through a barrier: on humanoid, XLA's CPU constant folding of the step
        # with the state's masses as constants gave NaN frames (not with them as
        # arguments, nor op by op)
        live = ps.replace(mass=jax.lax.optimization_barrier(ps.mass))
        return planar.cotangent(jax.vmap(step)(live, xi, xdi, a))

    dist = jax.vmap(lambda x: contact.get(sys, x).dist)(ps.x)
    return trained, ours, (ps.x_i, ps.xd_i, act), dist


@pytest.mark.parametrize("name", ["hopper", pytest.param("walker2d", marks=pytest.mark.slow)])
def test_spring_control_step_is_the_trained_step(name):
    """Every frame and joint coordinate of the step ILD trains with, to float32 round-off,
    with contacts active (some capsule ends below the floor): positions within 5e-7 and
    velocities within 2e-5 (measured on hopper: 1.4e-7 and 5.5e-6; walker2d 1.8e-7 and
    3.4e-6). Out-of-plane entries are exactly zero here."""
    trained, ours, args, dist = _control_steps(name)
    assert int((dist < 0).sum()) >= 2  # contacts in play
    want, got = jax.jit(trained)(*args), jax.jit(ours)(*args)
    assert_same_step(want, got, pos=5e-7, q=5e-7, moves=1.0)


# the trained step's reverse mode, compiled: ~2 minutes on one core; the default run checks
# the form over the links against this per-link form's VJP (tests/test_planar_links.py)
# and the link machinery against brax's VJP in 3-D (tests/test_spatial_links.py)
@pytest.mark.slow
def test_spring_control_step_vjp_is_the_trained_steps():
    """hopper, contacts active: the VJP in the centre-of-mass frames and the action, for a
    sine cotangent of the in-plane entries of every output, against the reverse mode of
    the step ILD trains with (hand_adjoint's VJPs) as a function of those frames, within
    1e-4 of each leaf's largest entry."""
    trained, ours, args, _ = _control_steps("hopper")
    assert_same_vjp(trained, ours, args)


@pytest.mark.slow  # two rollout-gradient compiles: ~2.5 minutes on one core
@pytest.mark.parametrize("name", ["hopper", "walker2d"])
def test_spring_planar_adjoint_is_the_same_rollout_and_gradient(name):
    """ILD's rollout loss and policy gradient over 16 steps (B = 8, the task's config, with
    and without planar_adjoint, whose planar_links goes with it): the same loss bit for bit
    (the task's own step computes the rollout) and every gradient leaf within 1e-5 of its
    largest entry (measured on hopper, per-link form: 3.2e-7)."""
    assert_same_rollout_gradient(name, {"planar_adjoint": False}, {"planar_adjoint": True})


def assert_same_rollout_gradient(name: str, a: dict, b: dict, rel: float = 1e-5,
                                 steps: int = 16):
    """ILD's rollout loss and policy gradient over `steps` steps of `name` (B = 8), its
    task's config with the fields `a` and with `b` (`task_config`'s overrides): the same
    loss bit for bit and every gradient leaf within `rel` of its largest entry, the
    gradient not all zero."""
    task = make_task(name)
    task = Task(spec=dataclasses.replace(task.spec, episode_length=steps), env=task.env)
    out = []
    for fields in (a, b):
        cfg = task_config(name, 8, fields)
        policy, goals, norm, params, k = speed_setup(task, cfg)
        loss = make_rollout_loss(cfg.physics(task), policy, goals, norm, cfg.config)
        init_keys = jax.random.split(k[2], 8)
        out.append(jax.jit(jax.value_and_grad(lambda p: loss(p, k[3], init_keys)[0]))(params))
    (want_l, want), (got_l, got) = out
    assert float(got_l) == float(want_l)
    flat = jax.tree_util.tree_flatten_with_path(want)[0]
    for (path, w), g in zip(flat, jax.tree_util.tree_leaves(got)):
        np.testing.assert_allclose(g, w, rtol=0, atol=rel * float(jnp.abs(w).max()),
                                   err_msg=jax.tree_util.keystr(path))
    assert float(jnp.abs(want["net"]["params"]["hidden_1"]["kernel"]).sum()) > 0
