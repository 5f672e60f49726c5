"""`lean_substeps`: brax's spring and positional substeps without the joint coordinates that
only a control step's last one needs. The same rollout and gradient, less work (XLA drops the
inverse kinematics of the other substeps), and clear refusals where a scene needs them."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from methods.ild.config import ILDConfig
from tasks import make_task
from tasks.physics import Plan, apply
from tasks.core import open_loop
from tasks.physics.transforms import lean_substeps_refusal, with_lean_substeps, with_substep_remat


def _rollout_and_grad(task, steps=12, batch=4):
    """An open-loop rollout of `batch` envs from reset under a varying action sequence: the
    loss (a smooth function of every step's world-frame pose and motion and observation)
    and its gradient in the actions, jitted."""
    env = task.env
    s0 = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(3), batch))
    acts = 0.9 * jnp.sin(jnp.arange(steps * batch * task.action_size, dtype=jnp.float32)
                         .reshape(steps, batch, task.action_size))

    def loss(a):
        _, (pos, vel, obs) = open_loop(jax.vmap(env.step), s0, a, lambda s: (
            s.pipeline_state.x.pos, s.pipeline_state.xd.vel, s.obs))
        return jnp.sum(jnp.sin(pos)) + 0.1 * jnp.sum(jnp.tanh(vel)) + jnp.sum(jnp.cos(obs))

    return jax.jit(jax.value_and_grad(loss))(acts)


def _step_and_vjp(step, ps, act):
    """One control step of a batch from pipeline states `ps`: its end state's q, qd and
    world-frame pose and motion, and the gradient of a smooth function of them in the
    incoming link frames and velocities and the actions, jitted."""
    def loss(x, xd, act):
        out = jax.vmap(step)(ps.replace(x=x, xd=xd), act)
        return (jnp.sum(jnp.sin(out.q)) + 0.1 * jnp.sum(jnp.tanh(out.qd))
                + jnp.sum(jnp.cos(out.x.pos)) + 0.1 * jnp.sum(jnp.tanh(out.xd.ang))), out
    (_, out), grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2), has_aux=True))(
        ps.x, ps.xd, act)
    return (out.q, out.qd, out.x.pos, out.x.rot, out.xd.vel, out.xd.ang), jax.tree.leaves(grad)


@pytest.mark.slow  # 4 compilations of a step's VJP per task: ~4 minutes for the two
@pytest.mark.parametrize("name", ["hopper", "reacher"])  # spring, positional
def test_lean_substeps_are_braxs_step_and_gradient(name):
    """One control step (4 substeps) of 8 envs, 10 steps after reset (hopper's foot on the
    ground): the end state and the gradient of a function of it in the incoming state and
    the actions agree with brax's step to float32 round-off, with and without each substep
    checkpointed (XLA fuses the leaner step differently, so not bit for bit)."""
    task = make_task(name)
    env = task.env
    s = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(3), 8))
    act = 0.9 * jnp.sin(jnp.arange(8 * task.action_size, dtype=jnp.float32)
                        ).reshape(8, task.action_size)
    step = jax.jit(jax.vmap(env.step))
    for _ in range(10):
        s = step(s, act)
    want, want_grad = _step_and_vjp(env.unwrapped.pipeline_step, s.pipeline_state, act)
    scale = max(float(jnp.max(jnp.abs(g))) for g in want_grad)
    assert scale > 1e-2 and float(jnp.max(jnp.abs(want[1] - s.pipeline_state.qd))) > 1e-3
    for remat in (True, False):
        lean = with_lean_substeps(task, remat=remat).env.unwrapped
        got, grad = _step_and_vjp(lean.pipeline_step, s.pipeline_state, act)
        for w, g in zip(want, got):
            np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-5)
        for w, g in zip(want_grad, grad):
            np.testing.assert_allclose(g, w, rtol=0, atol=1e-5 * scale)


@pytest.mark.slow  # a rollout gradient compiled twice; the default run checks the
# control step's value and gradient above
def test_lean_substeps_are_braxs_rollout_and_gradient():
    """12 control steps of 4 hopper envs from reset through ILD's default physics (each
    substep checkpointed) and through the lean copy: the loss (a smooth function of every
    step's world-frame pose and motion and observation) and its gradient in the actions agree
    to float32 round-off."""
    task = make_task("hopper")
    want_loss, want_grad = _rollout_and_grad(with_substep_remat(task))
    scale = float(jnp.max(jnp.abs(want_grad)))
    assert scale > 0.1  # the loss reaches the actions
    loss, grad = _rollout_and_grad(with_lean_substeps(task))
    np.testing.assert_allclose(loss, want_loss, rtol=1e-5)
    np.testing.assert_allclose(grad, want_grad, rtol=0, atol=1e-4 * scale)


def _atan2s(step, task, batch=2):
    """atan2 ops in the optimized XLA program of one control step of `batch` envs: brax
    reads joint angles with atan2 (`kinematics.inverse` for q, the joint forces for their
    limits), so dropped inverse kinematics show as fewer."""
    s = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))
    a = jnp.zeros((batch, task.action_size))
    hlo = jax.jit(jax.vmap(step)).lower(s.pipeline_state, a).compile().as_text()
    return hlo.count(" atan2(")


def test_lean_substeps_drop_the_inner_substeps_inverse_kinematics():
    """The point of the rewrite, read from XLA's optimized program of one hopper control step:
    brax's step is a scan whose body is one substep (as many atan2s as a substep alone: 8);
    the lean step is a scan of lean substeps and then the last, full substep, so it has more
    than one body's atan2s and fewer than two, the lean body lacking the inverse
    kinematics' (measured: 12)."""
    hopper = make_task("hopper")
    inner = hopper.env.unwrapped
    sub = _atan2s(lambda ps, a: inner._pipeline.step(inner.sys, ps, a), hopper)
    brax_step = _atan2s(inner.pipeline_step, hopper)
    lean = with_lean_substeps(hopper, remat=False).env.unwrapped
    lean_step = _atan2s(lean.pipeline_step, hopper)
    assert sub > 0 and brax_step == sub  # brax's step: one substep body, scanned
    # lean: a scan body without the inverse kinematics' atan2s, plus one full substep
    assert sub < lean_step < 2 * sub, (sub, brax_step, lean_step)


def test_lean_substeps_refuse_scenes_that_need_every_substeps_coordinates():
    """Generalized tasks integrate q, qd (nothing to drop), pointmass has no brax step, and a
    servo (an actuator with a position or velocity bias) reads q, qd in every substep: each
    refused with the field to leave off; a task already rewritten is refused as the other
    rewrites refuse it."""
    for name in ("acrobot", "swimmer", "pointmass"):
        with pytest.raises(ValueError, match=f"{name}.*lean_substeps"):
            with_lean_substeps(make_task(name))
    assert lean_substeps_refusal(make_task("hopper")) is None
    assert lean_substeps_refusal(make_task("inverted_pendulum")) is None
    servo = with_substep_remat(make_task("hopper"))  # a fresh copy whose sys we may edit
    inner = servo.env.unwrapped
    inner.sys = inner.sys.replace(actuator=inner.sys.actuator.replace(
        bias_q=inner.sys.actuator.bias_q.at[0].set(-1.0)))
    with pytest.raises(ValueError, match="bias_q"):
        with_lean_substeps(servo)
    with pytest.raises(ValueError, match="already has its own physics step"):
        with_lean_substeps(with_substep_remat(make_task("hopper")))


def test_a_plan_with_lean_substeps_builds_the_lean_copy(monkeypatch):
    """On, `apply` builds the lean copy, checkpointed as `substep_remat` says, in place of
    `with_substep_remat`; with the closed-form adjoint (which replaces brax's step) the plan
    is refused naming both fields."""
    from tasks.physics import Plan, apply, transforms
    with pytest.raises(ValueError, match="closed_form_adjoint differentiates.*lean_substeps"):
        Plan(closed_form_adjoint=True, lean_substeps=True)
    calls = []
    monkeypatch.setattr(transforms, "with_lean_substeps",
                        lambda t, remat: calls.append(("lean", remat)) or t)
    monkeypatch.setattr(transforms, "with_substep_remat", lambda t: calls.append("remat") or t)
    hopper = make_task("hopper")
    apply(hopper, Plan(lean_substeps=True))
    apply(hopper, Plan(lean_substeps=True, substep_remat=False))
    apply(hopper, Plan())
    assert calls == [("lean", True), ("lean", False), "remat"]


def test_speed_benchmark_lean_rows(apg_timed):
    """'lean' is three rows, each a group of its own: forward_lean and ild_lean time ILD on
    the lean physics, apg_lean brax's APG on it (its env's pipeline_step replaced, like with
    like); generalized tasks leave all three out."""
    from benchmarks import ild_speed as benchmark
    assert benchmark.expand_rows(("forward", "lean", "apg")) == (
        "forward", "forward_lean", "ild_lean", "apg_lean", "apg")
    timed = apg_timed
    rows = benchmark.run("hopper", batch=2, repeats=3, only=("apg", "apg_lean"))
    assert [r["what"] for r in rows] == ["apg", "apg_lean"] and timed == [False, True]
    assert benchmark.run("acrobot", batch=2, repeats=1, only=("lean",)) == []
    phys = apply(make_task("hopper"), Plan(lean_substeps=True))
    assert "pipeline_step" in vars(phys.env.unwrapped)


@pytest.mark.slow  # benchmark tool
def test_paired_times_lean_variants_against_apg_on_the_same_lean_physics():
    """benchmarks.ild_paired: variants that all set lean_substeps time APG on lean substeps, and
    APG's copy is not checkpointed (brax's APG does not rematerialize; ILD's does, as its
    default substep_remat says); a mix of lean and not is refused unless APG is brax's."""
    from benchmarks import ild_paired as paired
    base = paired.Setup(ILDConfig(num_envs=32))
    lean = {v: paired.parse_variant(v, 32) for v in ("lean_substeps", "lean_substeps,chunk=4")}
    assert paired.apg_physics(lean, base) == "lean_substeps"
    mixed = {v: paired.parse_variant(v, 32) for v in ("lean_substeps", "substep_remat")}
    with pytest.raises(ValueError, match=r"\['lean_substeps'\] set lean_substeps"):
        paired.apg_physics(mixed, base)
    assert paired.apg_physics(mixed, base, brax=True) == "brax"

    def remats(task):
        env = task.env
        s = env.reset(jax.random.PRNGKey(0))
        return str(jax.make_jaxpr(env.unwrapped.pipeline_step)(
            s.pipeline_state, jnp.zeros(task.action_size))).count("remat")
    hopper = make_task("hopper")
    assert remats(paired.apg_env(hopper, "lean_substeps")) == 0
    assert remats(apply(hopper, Plan(lean_substeps=True))) == 2  # both bodies
