"""The contract between the harness and a method plugin.

A method is a function (brax's `train()` shape):

    train(task: TaskView, demo: DemoView, config, ctx: RunContext, seed: int) -> TrainResult

It trains within `ctx.budget`, calls `ctx.report(policy, env_steps, metrics)` from its outer
loop (the harness may evaluate there, with the method's clock paused), and returns its FINAL
policy. It never computes its own leaderboard number. A method sees only what it declared in
`Uses`: the views it is handed enforce that (see bench/access.py).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Literal, Mapping


@dataclasses.dataclass(frozen=True)
class Uses:
    """What a method is allowed to read. The leaderboard prints this declaration."""

    demo_states: bool = False
    """Demo observations and matched states."""
    demo_actions: bool = False
    """Demo actions."""
    sim_gradients: bool = False
    """Gradients through the simulator (without it, env.step is wrapped in stop_gradient)."""
    true_reward: bool = False
    """The task's reward (without it, env rewards read NaN and demo rewards raise)."""
    sim_at_test: bool = False
    """The simulator and full state when acting at test time (planners)."""

    def describe(self) -> str:
        names = {"demo_states": "demo states", "demo_actions": "demo actions",
                 "sim_gradients": "sim gradients", "true_reward": "TRUE REWARD",
                 "sim_at_test": "SIM AT TEST"}
        used = [v for k, v in names.items() if getattr(self, k)]
        return ", ".join(used) or "nothing"


PolicyKind = Literal["jax", "host", "jax_state"]


@dataclasses.dataclass(frozen=True, eq=False)
class Policy:
    """A policy is a function plus a parameter pytree.

    kind 'jax':       act(params, obs, key, deterministic) -> action, for ONE observation,
                      pure JAX (the evaluator vmaps and scans it under jit).
    kind 'host':      act(params, obs_batch: np.ndarray, rng: np.random.Generator,
                      deterministic) -> actions np.ndarray, batched (torch/numpy methods).
    kind 'jax_state': act(params, env_state, key, deterministic) -> action: acts on the full
                      simulator state (planners); allowed only with Uses(sim_at_test=True).
    `act` should be one stable function object per run so the evaluator compiles it once.

    Stateful JAX policies (planners that warm-start from their previous plan) also set
    `init_memory(params, key) -> memory`; their act is then
    act(params, x, key, deterministic, memory) -> (action, memory), and the evaluator carries
    the memory through the episode (reset with the episode).
    """

    act: Callable[..., Any]
    params: Any
    kind: PolicyKind = "jax"
    init_memory: Callable[..., Any] | None = None


def start_memory(init_memory, params, act_key):
    """An episode's initial policy memory (None for a stateless policy); `act_key` is the
    episode's action key (the memory's key is derived from it)."""
    if init_memory is None:
        return None
    import jax
    return init_memory(params, jax.random.fold_in(act_key, 1))


def act_step(act, init_memory, params, x, key, deterministic, memory):
    """(action, memory) for one step of a stateless or stateful JAX policy."""
    if init_memory is None:
        return act(params, x, key, deterministic), memory
    return act(params, x, key, deterministic, memory)


@dataclasses.dataclass
class TrainResult:
    policy: Policy
    """The FINAL policy; the harness scores this one, never a best checkpoint."""
    env_steps: int = 0
    """Environment steps the method simulated for training."""
    metrics: Mapping[str, float] = dataclasses.field(default_factory=dict)
    """Last training metrics (namespaced: train/loss, grad/norm_raw, ...)."""


class Diverged(RuntimeError):
    """Raised (by a method or by the harness) when training produced non-finite numbers.
    The run is recorded as 'diverged' with its last valid evaluation."""


class InformationError(PermissionError):
    """A method read something it did not declare in its `Uses`."""


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    name: str
    train: Callable[..., TrainResult]
    config_cls: type
    """A frozen dataclass; defaults are the paper's values; __post_init__ validates."""
    uses: Uses
    description: str = ""
    version: str = "1"
    """Bump when the method's results change: part of the run id, so old cells re-run."""
    presets: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)
    """Named field overrides, e.g. {'cpu': {...}, 'paper': {}}."""
    task_overrides: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)
    """Per-task field overrides applied before presets and user overrides."""
    platform_overrides: Mapping[str, Mapping[str, Mapping[str, Any]]] = dataclasses.field(
        default_factory=dict)
    """Platform -> task -> field overrides, for the platform JAX computes on
    (`jax.default_backend()`: 'cpu', 'gpu', 'tpu'), applied after the task's overrides and
    before the preset and user overrides: a choice whose speed differs by accelerator. A field
    they turn off takes the task overrides of the fields that `requires` it along."""
    requires: Mapping[str, str] = dataclasses.field(default_factory=dict)
    """Field -> the field it needs on (e.g. a piece of a rewrite -> the rewrite): where a
    task override turned the first on and a preset or the user turns the second off, the
    first goes back to its default with it (the user asked for neither); set by the user
    or a preset, the config's own check refuses the pair."""
    reference: bool = False
    """True for references that are not imitation methods (true reward / sim at test)."""
    min_env_steps: int | None = None
    """The env steps the method's own paper trains for, if it needs that many to be judged
    (off-policy RL learners): a leaderboard cell whose median env steps fall below it is
    marked as starved, with a footnote."""
