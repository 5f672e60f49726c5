"""Floors: what a policy that learned nothing scores on each task, by the shared evaluator.

    zero_action   all-zero actions every step
    demo_replay   the demo's actions replayed open loop, step t playing a_t, from each
                  evaluation episode's own initial state

Each entry also holds the mean episode length (steps before termination), and the entry
holds the uniform random policy's own (`random`: normalized 0 by construction), so a method
that scores below the random policy can be shown to fall earlier than it does.

All are scored exactly as the expert and random references are (the shared evaluator,
`bench.expert.REFERENCE_EPISODES` deterministic episodes from `REFERENCE_SEED`) and stored
beside the transfer references (`<references>/<task>.floors.json`, keyed by the demo's
sha256, so a new demo gets new floors). A method that does not beat `zero_action` on a task
has learned nothing there; a task whose `zero_action` scores above `WEAK_ABOVE` normalized
is weakly discriminative (reacher: its random reference is mostly control cost).
"""
from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np

from bench.api import Policy
from bench.evaluator import EvalConfig, Evaluator
from tasks.core import Task
from tasks.demo import Demo

FLOORS = ("zero_action", "demo_replay")
"""The floor rows a table prints; the entry's `random` is the normalization's zero."""
WEAK_ABOVE = 0.8
"""A task whose zero_action floor scores above this (normalized) is weakly discriminative."""


def zero_action_policy(action_size: int) -> Policy:
    return Policy(act=_zero_act(action_size), params=())


@functools.lru_cache(maxsize=None)
def _zero_act(action_size: int):
    def act(params, obs, key, deterministic):
        return jnp.zeros((action_size,))
    return act


def _replay_act(params, obs, key, deterministic, t):
    """The demo's action a_t (the last one held past the demo's end); memory = t."""
    return params[jnp.minimum(t, params.shape[0] - 1)], t + 1


def _replay_start(params, key):
    return jnp.int32(0)


def demo_replay_policy(actions: np.ndarray) -> Policy:
    """Open-loop replay of one trajectory's actions (T, A)."""
    return Policy(act=_replay_act, params=jnp.asarray(actions, jnp.float32),
                  init_memory=_replay_start)


def floors(task: Task, demo: Demo, ref_dir: str | None = None,
           compute: bool = True) -> dict[str, dict] | None:
    """{floor: {'return', 'normalized', 'length'}} for `task` with `demo`'s references (the
    FLOORS and `random`): read from the references folder, or computed by the shared
    evaluator and stored there (`compute`; also where a stored entry lacks the random policy
    or the lengths); None where they are not stored and `compute` is False."""
    from bench.evaluator import random_policy
    from bench.expert import REFERENCE_EPISODES, REFERENCE_SEED
    from bench.transfer import load_references, store_reference
    file = f"{task.name}.floors.json"
    entry = load_references(file, ref_dir).get(demo.sha256)
    if not compute or (entry is not None and _complete(entry)):
        return entry
    ev = Evaluator(task, EvalConfig(num_episodes=REFERENCE_EPISODES, deterministic=True),
                   demo.expert_return, demo.random_return)
    entry = {}
    for name, policy in (("zero_action", zero_action_policy(task.action_size)),
                         ("demo_replay", demo_replay_policy(np.asarray(demo.actions[0]))),
                         ("random", random_policy(task.action_size))):
        r = ev.evaluate(policy, REFERENCE_SEED)
        entry[name] = {"return": r.mean_return, "normalized": r.mean_normalized,
                       "length": r.mean_length}
    store_reference(file, demo.sha256, entry, ref_dir=ref_dir)
    return entry


def _complete(entry: dict) -> bool:
    return "random" in entry and all("length" in v for v in entry.values())


def weakly_discriminative(entry: dict | None) -> bool:
    return bool(entry) and entry["zero_action"]["normalized"] > WEAK_ABOVE
