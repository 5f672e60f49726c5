"""A method gets only what it declared."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.access import DemoView, TaskView
from bench.api import InformationError, Uses
from tasks import make_task
from tasks.demo import load_demo


def _view(uses):
    task = make_task("pointmass")
    return TaskView(task, uses, "m"), DemoView(load_demo(task.spec.demo_path, task), uses, "m")


def test_reward_is_hidden_without_true_reward():
    tv, dv = _view(Uses(demo_states=True))
    assert (tv.state_size, tv.episode_length) == (2, 128)   # public task facts pass through
    s = tv.env.step(tv.env.reset(jax.random.PRNGKey(0)), jnp.zeros(1))
    assert np.isnan(s.reward)
    with pytest.raises(InformationError, match="demo.rewards.*true_reward"):
        dv.rewards
    tv2, dv2 = _view(Uses(true_reward=True))
    s2 = tv2.env.step(tv2.env.reset(jax.random.PRNGKey(0)), jnp.zeros(1))
    assert np.isfinite(s2.reward) and dv2.returns.shape == (1,)


def test_undeclared_demo_fields_raise():
    _, dv = _view(Uses(demo_states=True))
    assert dv.states.shape == (1, 129, 2)
    with pytest.raises(InformationError, match="'m' read demo.actions.*demo_actions"):
        dv.actions
    _, dv = _view(Uses())
    with pytest.raises(InformationError, match="demo_states"):
        dv.obs
    # the length and the initial states are public task information, open to every method
    assert dv.length == 128 and dv.init_keys.shape == (1, 2)   # num_demos = 1
    # a field no demo has is an ordinary AttributeError naming it (hasattr and getattr's
    # default rely on it; planted fault: the error raised without the name)
    with pytest.raises(AttributeError) as e:
        dv.no_such_field
    assert e.value.args == ("no_such_field",) and getattr(dv, "no_such_field", 3) == 3


def _grad_through_env(env, actions=None):
    # built here, not as a default argument: importing this module starts no JAX backend, so
    # mutmut's fork server (which collects the tests) stays fork-safe (docs/ci.md)
    actions = 0.5 * jnp.ones((5, 1)) if actions is None else actions
    s0 = env.reset(jax.random.PRNGKey(0))

    def f(a):
        s, _ = jax.lax.scan(lambda s, a: (env.step(s, a), None), s0, a)
        return s.obs[0]
    return jax.grad(f)(actions)


def test_no_sim_gradients_without_the_declaration():
    tv, _ = _view(Uses())
    assert float(jnp.abs(_grad_through_env(tv.env)).sum()) == 0.0
    tv, _ = _view(Uses(sim_gradients=True))
    assert float(jnp.abs(_grad_through_env(tv.env)).sum()) > 0.0


def _step_tangent(env, a):
    """The tangent of one step's observation along all-ones action directions, from reset
    (one jitted forward-mode step: what the view's physics gradient gate has to zero)."""
    s0 = env.reset(jax.random.PRNGKey(0))
    return jax.jit(lambda a: jax.jvp(lambda x: env.step(s0, x).obs, (a,),
                                     (jnp.ones_like(a),))[1])(a)


def test_a_transformed_view_keeps_its_gates():
    """tasks.core's transforms build a fresh env from the task's spec; handed a method's view
    they must hand back one gated the same way, or a method using them (a physics plan's
    rewrites, ILD's joint_limits=False) would see the true reward and the physics gradient its
    Uses withheld."""
    from tasks.core import Task, without_joint_limits
    from tasks.physics.transforms import with_small_dots, with_substep_remat
    task = make_task("acrobot")
    a = 0.5 * jnp.ones(task.action_size)

    def transform(t):  # two transforms, each building a fresh env
        return with_small_dots(with_substep_remat(t))

    assert isinstance(transform(task), Task)  # a plain task stays plain
    hidden = transform(TaskView(task, Uses(demo_states=True), "m"))
    assert isinstance(hidden, TaskView)
    s = jax.jit(hidden.env.step)(hidden.env.reset(jax.random.PRNGKey(0)), a)
    assert np.isnan(s.reward) and s.metrics == {}
    cut = transform(TaskView(task, Uses(true_reward=True), "m"))
    assert np.isfinite(cut.env.reset(jax.random.PRNGKey(0)).reward)
    assert float(jnp.abs(_step_tangent(cut.env, a)).sum()) == 0.0
    free = transform(TaskView(task, Uses(sim_gradients=True), "m"))
    assert float(jnp.abs(_step_tangent(free.env, a)).sum()) > 0.0
    limited = make_task("inverted_pendulum")
    free = without_joint_limits(TaskView(limited, Uses(), "m"))
    assert isinstance(free, TaskView) and free.env.unwrapped.sys.dof.limit is None
    assert np.isnan(free.env.reset(jax.random.PRNGKey(0)).reward)


def test_a_view_runs_the_plan_only_for_a_method_that_differentiates_the_physics():
    """A view handed a physics plan applies it where the method declares `sim_gradients`
    (its own pipeline_step: the plan's rewritten step) and a copy made of it without joint
    limits keeps the plan; a method that does not differentiate through the physics steps
    the task itself, plan or not. Planted fault: `regated` dropping the plan."""
    from tasks.core import without_joint_limits
    from tasks.physics import plan_for
    task = make_task("swimmer")  # joint limits to remove
    plan = plan_for("swimmer", "cpu")
    assert plan.small_dots
    view = TaskView(task, Uses(sim_gradients=True), "m", plan)
    assert view.plan == plan and "pipeline_step" in vars(view.env.unwrapped)
    free = without_joint_limits(view)
    assert free.plan == plan and "pipeline_step" in vars(free.env.unwrapped)
    assert free.env.unwrapped.sys.dof.limit is None
    other = TaskView(task, Uses(demo_states=True), "m", plan)
    assert other.plan is None and "pipeline_step" not in vars(other.env.unwrapped)
    assert "pipeline_step" not in vars(task.env.unwrapped)


def test_a_copy_of_a_view_keeps_its_training_dynamics():
    """A copy a method makes of its view (a `tasks.core` transform, which hands `regated` a
    fresh task) steps the same changed dynamics as the view: a bias the method must cancel
    stays in the copy's env. Planted fault: `regated` dropping the training dynamics (the
    copy would train nominal)."""
    from bench.perturb import parse_dynamics
    task = make_task("pointmass")
    bias = parse_dynamics("action_bias:0.3", task)
    view = TaskView(task, Uses(demo_states=True), "m", dynamics=bias)
    copy = view.regated(make_task("pointmass"))
    assert copy.dynamics == bias

    def obs_after(env):
        s = env.reset(jax.random.PRNGKey(0))
        return np.asarray(env.step(s, jnp.zeros(task.action_size)).obs)
    assert np.allclose(obs_after(copy.env), obs_after(view.env))
    assert not np.allclose(obs_after(copy.env), obs_after(task.env))


def test_reward_terms_in_the_metrics_are_hidden_without_true_reward():
    """Brax tasks carry their reward's terms in `state.metrics` (hopper: reward_forward,
    reward_ctrl, ...): a method that did not declare true_reward sees none of them, after
    reset or step. Planted fault: the wrapper hiding `reward` but keeping `metrics`."""
    task = make_task("hopper")
    assert task.env.reset(jax.random.PRNGKey(0)).metrics  # there is something to hide
    blind = TaskView(task, Uses(demo_states=True), "m").env
    s = blind.reset(jax.random.PRNGKey(0))
    assert s.metrics == {}
    assert blind.step(s, jnp.zeros(task.action_size)).metrics == {}
