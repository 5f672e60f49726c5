"""What a method is handed: views of the task and the demo that enforce its `Uses`.

- No true_reward: env rewards read NaN (any use poisons the loss visibly), reward terms
  in `state.metrics` are dropped, and `demo.rewards`/`demo.returns` raise.
- No sim_gradients: `env.step` is wrapped in stop_gradient, so gradients through the
  physics are exactly zero. With sim_gradients: the env runs the task's physics plan
  (`tasks.physics.plan`, chosen by the runner), the same function and gradient as brax's
  step to float32 round-off, at the cost the plan buys.
- No demo_states / demo_actions: reading those demo fields raises InformationError.

A run with changed training dynamics (`--train-dynamics`, `bench.perturb.parse_dynamics`)
hands every method the env of those dynamics: the physical parameters scaled in before the
plan is applied (its rewrites then step the changed physics), the noise wrapped around it.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import tasks  # noqa: F401  (before brax: tasks/__init__.py keeps brax's import noise quiet)
from brax.envs.base import State, Wrapper

from bench.api import InformationError, Uses
from tasks.core import Task
from tasks.demo import Demo


class HideReward(Wrapper):
    def _hide(self, s: State) -> State:
        return s.replace(reward=jnp.full_like(jnp.asarray(s.reward, jnp.float32), jnp.nan),
                         metrics={})

    def reset(self, rng: jax.Array) -> State:
        return self._hide(self.env.reset(rng))

    def step(self, state: State, action: jax.Array) -> State:
        return self._hide(self.env.step(state, action))


class NoSimGradient(Wrapper):
    def step(self, state: State, action: jax.Array) -> State:
        return jax.lax.stop_gradient(self.env.step(state, action))


class TaskView:
    """The task as a method sees it: `env` is gated, and for a method that differentiates
    through the physics (`sim_gradients`) it runs `plan` (a `tasks.physics.Plan`; None:
    the task's env as it is); the rest is plain task information. A copy a method makes of
    it with a `tasks.core` transform (`without_joint_limits`) comes back behind the same
    gates, with the same plan (`regated`). `dynamics` (a `bench.perturb.Perturbation`, None:
    nominal): the changed dynamics the method trains in."""

    def __init__(self, task: Task, uses: Uses, method: str, plan=None, dynamics=None):
        if dynamics is not None:
            from bench.perturb import physics_scaled
            task = physics_scaled(task, dynamics)
        if plan is not None and uses.sim_gradients:
            from tasks.physics import apply
            task = apply(task, plan)
        self.plan = plan if uses.sim_gradients else None
        self.dynamics = dynamics
        env = task.env
        if dynamics is not None:
            from bench.perturb import with_noise
            env = with_noise(env, dynamics)
        if not uses.true_reward:
            env = HideReward(env)
        if not uses.sim_gradients:
            env = NoSimGradient(env)
        self.env = env
        self.spec = task.spec
        self.name = task.name
        self.episode_length = task.episode_length
        self.obs_size = task.obs_size
        self.action_size = task.action_size
        self.state_size = task.state_size
        self.matched_state = task.matched_state
        self._uses = uses
        self._method = method

    def regated(self, task: Task) -> "TaskView":
        """`task` (a copy built from this view's spec) behind this view's gates, with its
        plan and its training dynamics: the transforms build a fresh env from the spec,
        which would otherwise drop them."""
        return TaskView(task, self._uses, self._method, self.plan, self.dynamics)


class DemoView:
    """The demo as a method sees it. `k` trajectories (default: the top-1 demo)."""

    _NEEDS = {"obs": "demo_states", "states": "demo_states", "actions": "demo_actions",
              "rewards": "true_reward", "returns": "true_reward"}

    def __init__(self, demo: Demo, uses: Uses, method: str, num_demos: int = 1):
        self._demo = demo.top(num_demos)
        self._uses = uses
        self._method = method
        self.num_demos = num_demos
        self.length = demo.length
        self.init_keys = self._demo.init_keys  # initial states are public task information

    def __getattr__(self, name):
        need = DemoView._NEEDS.get(name)
        if need is None:
            raise AttributeError(name)
        if not getattr(self._uses, need):
            raise InformationError(
                f"method {self._method!r} read demo.{name} but did not declare {need}; "
                f"add Uses({need}=True) to its MethodSpec (the leaderboard will show it)")
        return getattr(self._demo, name)
