"""`spatial_links`: brax's spring step of ant's scene (a free root and hinges) with every
entry of every vector an array over the links (`tasks.spatial_links`). Its constants, the
same control step and VJP as the step ILD trains with, the same rollout gradient, and the
scenes and configs it refuses."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tasks.planar as planar
import tasks.spatial_links as spatial_links
from methods.ild.config import ILDConfig
from tasks import make_task
from tasks.core import spatial_adjoint_refusal, with_spatial_adjoint
from tests.test_planar_spring import _control_steps as control_steps
from tests.test_planar_spring import assert_same_rollout_gradient, rollout_physics


def test_spatial_scene_reads_ant_over_its_links():
    """ant's nine links (torso; four hips, each with its ankle below): the parent matrix, the
    free root's joint constants all zero (brax's `_free` has no force) and its dofs unread,
    every hinge limited, masses and inverse inertias of one (ant's spring scales are 1, so
    brax divides by m ** 0 and turns I ** 0), the four feet spheres (no half-length, the
    Python 0.0) and the one entry of the flattened inverse inertias each foot's contact
    reads: link 0's (0, 2), (1, 1), (2, 0), (2, 2) for feet 2, 4, 6, 8 (identity entries
    0, 1, 0, 1)."""
    ls = spatial_links.spatial_scene(make_task("ant").env.unwrapped.sys)
    lk, cs = ls.links, ls.contacts
    want = np.zeros((9, 9), np.float32)
    for child, parent in enumerate([-1, 0, 1, 0, 3, 0, 5, 0, 7]):
        if parent >= 0:
            want[parent, child] = 1
    np.testing.assert_array_equal(lk.parent, want)
    np.testing.assert_array_equal(lk.root, [1] + [0] * 8)
    assert lk.full and lk.unit_inertia and lk.mass == 1.0
    for field in (lk.stiffness, lk.vel_damping, lk.ang_damping, lk.limit_stiffness):
        assert field[0] == 0.0 and np.all(field[1:] > 0)
    assert all(a[0] == 0.0 for a in lk.spring_axis)
    norms = np.linalg.norm(np.stack([np.broadcast_to(a, 9) for a in lk.spring_axis]), axis=0)
    np.testing.assert_allclose(norms[1:], 1.0, rtol=1e-6)
    assert lk.turned_axis == lk.slide0 == lk.slide1 == (0.0, 0.0, 0.0)
    assert lk.dof_turn == (-1, *range(6, 14)) and lk.dof_slides == ((-1, -1),) * 9
    assert lk.lo[0] == -np.inf and lk.hi[0] == np.inf and np.all(lk.lo[1:] < lk.hi[1:])
    np.testing.assert_array_equal(cs.to_contacts.argmax(axis=0), [2, 4, 6, 8])
    assert cs.half == 0.0 and cs.inv_mass == 1.0
    assert cs.flat_entries == ((0, 2), (1, 1), (2, 0), (2, 2))
    assert ls.scene.gravity == (0.0, 0.0, planar._f32(-9.81))


def _control_steps(batch: int = 8):
    """`tests.test_planar_spring._control_steps` for ant and the form over the links: the
    step ILD trains with without spatial_links (hand_adjoint's spring substep, lean
    substeps) and `tasks.spatial_links.control_step`."""
    def form(sys, n):
        ls = spatial_links.spatial_scene(sys)
        return lambda xi, xdi, a: spatial_links.control_step(ls, sys, xi, xdi, a, n)
    return control_steps("ant", form, "spatial_links", batch)


def test_spatial_control_step_is_the_trained_step():
    """Every frame and joint coordinate of the step ILD trains with, to float32 round-off,
    feet on the floor: positions and rotations within 5e-7, velocities within 3e-5 (measured,
    session 76: 1.5e-7 and 1.0e-5, joint velocities up to 1.5 rad/s)."""
    trained, ours, args, dist = _control_steps()
    assert int((dist < 0).sum()) >= 8  # contacts in play
    want, got = jax.jit(trained)(*args), jax.jit(ours)(*args)
    for name, w, g in zip(planar.OUTPUTS, want[0], got[0]):
        tol = 3e-5 if name in ("xd", "xd_i", "jd") else 5e-7
        for wk, gk in zip(w, g):
            np.testing.assert_allclose(gk, wk, rtol=0, atol=tol, err_msg=name)
    np.testing.assert_allclose(got[1], want[1], rtol=0, atol=5e-7)
    np.testing.assert_allclose(got[2], want[2], rtol=0, atol=3e-5)
    assert float(jnp.abs(got[2]).max()) > 0.5  # the envs move


def _tangent(rot, g):
    """`g` less its component along the unit quaternion `rot` (per link)."""
    return g - rot * jnp.sum(rot * g, axis=-1, keepdims=True)


# the trained step's reverse mode and the form's, compiled: ~1.5 minutes on one core
def test_spatial_control_step_vjp_is_the_trained_steps():
    """Feet on the floor: the VJP in the centre-of-mass frames and the action, for a sine
    cotangent of every output, within 1e-4 of each leaf's largest entry of the trained
    step's (hand_adjoint's VJPs), the input rotation's cotangent along the unit sphere (brax's
    inverse inertia R I R^T is |q|^4 I off it, which the form writes as I: the one direction
    they differ in, and one the previous step's normalization takes out of every gradient
    it passes back)."""
    trained, ours, args, _ = _control_steps()
    _, want_pull = jax.vjp(trained, *args)
    got, got_pull = jax.vjp(ours, *args)
    ct = jax.tree.map(lambda v: jnp.sin(7.0 * jnp.arange(v.size, dtype=v.dtype)
                                        ).reshape(v.shape), got)
    (w_xi, w_xdi, w_a), (g_xi, g_xdi, g_a) = want_pull(ct), got_pull(ct)
    rot = args[0].rot
    for kind, w, g in (("pos", w_xi.pos, g_xi.pos),
                       ("rot", _tangent(rot, w_xi.rot), _tangent(rot, g_xi.rot)),
                       ("vel", w_xdi.vel, g_xdi.vel), ("ang", w_xdi.ang, g_xdi.ang),
                       ("act", w_a, g_a)):
        scale = float(jnp.abs(w).max())
        assert scale > 1e-2, kind
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-4 * scale, err_msg=kind)


@pytest.mark.slow  # two rollout-gradient compiles of ant: ~3 minutes on one core
def test_spatial_links_is_the_same_rollout_and_gradient():
    """ILD's rollout loss and policy gradient over 16 steps on ant (B = 8, the task's
    config, spatial_links off and on): the same loss bit for bit (the task's own step
    computes the rollout) and every gradient leaf within 3e-5 of its largest entry
    (measured, session 76: 1.25e-5, two of hidden_0's 512 bias entries over 1e-5)."""
    assert_same_rollout_gradient("ant", {"spatial_links": False}, {"spatial_links": True},
                                 rel=3e-5)


def test_spatial_links_is_on_for_ant_on_a_cpu():
    """Since session 76 ILD trains ant with `spatial_links` on a CPU (SPATIAL_LINKS_TASKS)
    and no other task does; `--set spatial_links=false` turns it off alone (the forward's
    hand_adjoint and its pieces stay), and the rollout physics differentiates through the
    form over the links (the step's forward is the task's own: brax's values)."""
    import dataclasses

    from bench.plugins import build_config, get_method
    from methods.ild.config import SPATIAL_LINKS_TASKS, TASK_OVERRIDES
    assert SPATIAL_LINKS_TASKS == ("ant",)
    assert [t for t, over in TASK_OVERRIDES.items() if over.get("spatial_links")] == ["ant"]
    ild = get_method("ild")
    ant = build_config(ild, "ant", "cpu", {}, platform="cpu")
    assert ant.spatial_links and ant.hand_adjoint and ant.saved_residuals
    off = build_config(ild, "ant", "cpu", {"spatial_links": "false"}, platform="cpu")
    assert off == dataclasses.replace(ant, spatial_links=False)
    step = rollout_physics(make_task("ant"), ant).env.unwrapped.pipeline_step
    assert "_step_with_adjoint" in step.__qualname__  # the task's step, the links' VJP
    step = rollout_physics(make_task("ant"), off).env.unwrapped.pipeline_step
    assert "_rebuilt_substep_loop" in step.__qualname__  # hand_adjoint's substeps


def test_spatial_links_is_refused_where_it_does_not_apply():
    """humanoid (2- and 3-dof joints), hopper (a planar root: a 3-dof joint) and
    inverted_pendulum (the positional backend) are refused by name, and the config refuses
    it beside another rewrite of the step's backward."""
    assert spatial_adjoint_refusal(make_task("ant")) is None
    for name, why in (("humanoid", "neither a free root nor a 1-dof joint"),
                      ("hopper", "neither a free root nor a 1-dof joint"),
                      ("inverted_pendulum", "runs 'positional' physics")):
        with pytest.raises(ValueError, match=f"task {name!r}.*{why}.*leave it False"):
            with_spatial_adjoint(make_task(name))
    for other in ("planar_adjoint", "small_dots", "closed_form_adjoint"):
        with pytest.raises(ValueError, match=f"spatial_links .*; {other} rewrites another"):
            ILDConfig(spatial_links=True, **{other: True})
    ILDConfig(spatial_links=True, hand_adjoint=True, lean_substeps=True)
