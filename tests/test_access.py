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


def _grad_through_env(env):
    s0 = env.reset(jax.random.PRNGKey(0))

    def f(a):
        s, _ = jax.lax.scan(lambda s, a: (env.step(s, a), None), s0, a)
        return s.obs[0]
    return jax.grad(f)(0.5 * jnp.ones((5, 1)))


def test_no_sim_gradients_without_the_declaration():
    tv, _ = _view(Uses())
    assert float(jnp.abs(_grad_through_env(tv.env)).sum()) == 0.0
    tv, _ = _view(Uses(sim_gradients=True))
    assert float(jnp.abs(_grad_through_env(tv.env)).sum()) > 0.0
