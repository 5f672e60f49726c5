"""Shims that let brax 0.14.2 train on newer JAX (the accelerator image ships jax 0.11).

The project pins jax 0.7.2, where both names below exist and `apply()` changes nothing.
Newer JAX removed `jax.device_put_replicated` (brax's PPO uses it) and the `a_min`/`a_max`
keywords of `jnp.clip` (brax's swimmer fluid model uses them). `apply()` restores both
with their documented meaning, only where they are missing; tests/test_expert.py checks
them against the originals on the pinned JAX.
"""
from __future__ import annotations

import inspect

import jax
import jax.numpy as jnp

_clip = jnp.clip


def device_put_replicated(x, devices):
    """One copy of each leaf per device, stacked on a new leading axis (what pmap takes)."""
    return jax.tree.map(lambda a: jax.device_put(jnp.stack([jnp.asarray(a)] * len(devices))), x)


def clip_compat(arr=None, min=None, max=None, *, a=None, a_min=None, a_max=None, **kw):
    """jnp.clip accepting both the old (a, a_min, a_max) and new (arr, min, max) keywords."""
    arr = a if arr is None else arr
    return _clip(arr, a_min if min is None else min, a_max if max is None else max, **kw)


def apply() -> list[str]:
    """Install the missing names; returns which were installed."""
    done = []
    if not hasattr(jax, "device_put_replicated"):
        jax.device_put_replicated = device_put_replicated
        done.append("jax.device_put_replicated")
    if "a_min" not in inspect.signature(jnp.clip).parameters:
        jnp.clip = clip_compat
        done.append("jnp.clip(a_min=, a_max=)")
    return done
