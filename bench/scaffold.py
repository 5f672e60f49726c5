"""`ildbench new-method NAME`: a minimal, installable method plugin to start from.

The package it writes (`ildbench-NAME/`) registers NAME through the `ildbench.methods` entry
point, so installing it (`pip install -e ./ildbench-NAME`) is all ildbench needs to list,
run, sweep and gate it. Its method is a real one, small enough to read in a minute: a
linear-tanh policy regressed onto the demo's actions with Adam (behaviour cloning with a
linear model), reporting to the harness between jitted chunks of updates, as a method must.
It passes `ildbench conform` as written; the author replaces its update with theirs.

Written files: pyproject.toml, README.md, the method module, a test that runs the
conformance check, a canary suite for the author's own CI gate, and a CI example.
"""
from __future__ import annotations

import keyword
import os
import re

NAME_RE = re.compile(r"[a-z][a-z0-9_]{0,39}")


class ScaffoldError(ValueError):
    pass


def check_name(name: str) -> str:
    """A method name that is a valid Python identifier and not a registered method."""
    from bench.plugins import all_methods
    if not NAME_RE.fullmatch(name or "") or keyword.iskeyword(name):
        raise ScaffoldError(f"method name {name!r} must be lower case letters, digits and "
                            "underscores, starting with a letter (it names a Python "
                            "package), e.g. mymethod")
    if name in all_methods():
        raise ScaffoldError(f"method {name!r} is already registered; pick another name "
                            f"(registered: {', '.join(sorted(all_methods()))})")
    return name


PYPROJECT = '''[build-system]
requires = ["setuptools>=68"]
build-backend = "setuptools.build_meta"

[project]
name = "ildbench-{name}"
version = "0.1.0"
description = "{name}: an imitation method for the ildbench harness"
requires-python = ">=3.11"
dependencies = ["ildbench"]

[project.optional-dependencies]
test = ["pytest>=8"]

# How ildbench finds the method: `ildbench methods` lists it once this package is installed.
[project.entry-points."ildbench.methods"]
{name} = "ildbench_{name}:METHOD"

[tool.setuptools]
packages = ["ildbench_{name}"]
'''

MODULE = '''"""{name}: an imitation method for ildbench.

As written: a linear-tanh policy regressed onto the demo's actions with Adam (behaviour
cloning with a linear model). Replace `update` (and the config) with your method; keep the
loop's shape: ask `ctx.should_stop` before each chunk of work, `ctx.report` after it (the
harness may evaluate there, with your clock paused), and return the FINAL policy.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import optax

from bench.api import MethodSpec, Policy, TrainResult, Uses


@dataclasses.dataclass(frozen=True)
class Config:
    learning_rate: float = 1e-2
    """Adam step size."""
    updates: int = 600
    """Gradient steps on the demo's (observation, action) pairs."""
    chunk: int = 50
    """Updates per jitted call; the harness hears from the method once per call."""

    def __post_init__(self):
        for field in ("learning_rate", "updates", "chunk"):
            if not getattr(self, field) > 0:
                raise ValueError(f"{{field}} must be > 0, got {{getattr(self, field)}}")


def act(params, obs, key, deterministic):
    """One observation -> one action in [-1, 1] (pure JAX: the evaluator jits and vmaps it)."""
    x = (obs - params["mean"]) / params["std"]
    return jnp.tanh(x @ params["w"] + params["b"])


def train(task, demo, config: Config, ctx, seed: int) -> TrainResult:
    # o_0..o_{{T-1}} with the actions taken in them, over all demos handed to the method
    obs = jnp.asarray(demo.obs[:, :-1]).reshape(-1, task.obs_size)
    actions = jnp.asarray(demo.actions).reshape(-1, task.action_size)
    key = jax.random.PRNGKey(seed)
    params = {{"mean": obs.mean(0), "std": jnp.maximum(obs.std(0), 1e-3),
              "w": 0.01 * jax.random.normal(key, (task.obs_size, task.action_size)),
              "b": jnp.zeros(task.action_size)}}
    opt = optax.adam(config.learning_rate)

    def loss(p):
        trainable = {{**p, "mean": jax.lax.stop_gradient(p["mean"]),
                     "std": jax.lax.stop_gradient(p["std"])}}
        pred = jax.vmap(lambda o: act(trainable, o, None, True))(obs)
        return jnp.mean(jnp.sum((pred - actions) ** 2, -1))

    def update(carry, _):
        p, s = carry
        value, grads = jax.value_and_grad(loss)(p)
        grads = {{**grads, "mean": jnp.zeros_like(grads["mean"]),
                 "std": jnp.zeros_like(grads["std"])}}
        steps, s = opt.update(grads, s)
        return (optax.apply_updates(p, steps), s), value

    @functools.partial(jax.jit, static_argnums=1)
    def chunk(carry, length):
        return jax.lax.scan(update, carry, None, length=length)

    carry, done = (params, opt.init(params)), 0
    while done < config.updates and not ctx.should_stop(0):  # 0: it never steps the env
        n = min(config.chunk, config.updates - done)
        carry, losses = chunk(carry, n)
        done += n
        ctx.report(Policy(act, carry[0]), env_steps=0,
                   metrics={{"train/loss": losses[-1], "train/updates": done}})
    return TrainResult(Policy(act, carry[0]), env_steps=0, metrics={{"train/updates": done}})


METHOD = MethodSpec(
    name="{name}", train=train, config_cls=Config,
    uses=Uses(demo_states=True, demo_actions=True),  # what it reads; the harness enforces it
    description="linear-tanh behaviour cloning (the ildbench new-method scaffold)",
    version="1",  # bump when a change alters results: it is part of every run id
    presets={{"cpu": {{}}}})
'''

TEST = '''"""The plugin passes ildbench's conformance check (runs, respects the budget, compiles its
update once, is deterministic) and is registered under its name."""
from bench.conformance import conform, render
from bench.plugins import all_methods


def test_{name}_is_registered():
    assert "{name}" in all_methods()


def test_{name}_conforms():
    found = conform("{name}", task="pointmass")
    assert all(f.passed is not False for f in found), render("{name}", found)
'''

CANARY = '''# The CI gate of {name}: `ildbench check --suite canary.toml` compares these runs with
# canary_reference.json (written by `ildbench check --suite canary.toml --update`; commit it).
# Env-step budgets and fixed seeds: the scores do not depend on the machine's speed.
seeds = [0, 1]
tolerance = 0.05

[[canary]]
method = "{name}"
task = "pointmass"
env_steps = 20000

[[canary]]
method = "{name}"
task = "inverted_pendulum"
env_steps = 20000
'''

CI = '''# CI example: test the plugin, then gate its scores on the committed canary reference.
name: ci
on: [push, pull_request]
jobs:
  test:
    runs-on: ubuntu-latest
    steps:
      - uses: actions/checkout@v4
      - uses: actions/setup-python@v5
        with:
          python-version: "3.11"
      - run: pip install -e ".[test]"
      - run: python -m pytest -q
      - run: ildbench check --suite canary.toml
'''

README = '''# ildbench-{name}

An imitation method for [ildbench](https://pypi.org/project/ildbench/), made by
`ildbench new-method {name}`.

    pip install -e .                              # registers "{name}" with ildbench
    ildbench methods                              # lists it
    ildbench conform --method {name}              # the plugin check
    ildbench sweep --methods {name} --tasks pointmass --seeds 1 --budget-steps 20000
    ildbench check --suite canary.toml --update   # write canary_reference.json; commit it
    ildbench check --suite canary.toml            # the CI gate (.github/workflows/ci.yml)

The method lives in `ildbench_{name}/__init__.py`.
'''


def files(name: str) -> dict[str, str]:
    """{relative path: text} of the scaffold for method `name`."""
    return {"pyproject.toml": PYPROJECT.format(name=name),
            "README.md": README.format(name=name),
            f"ildbench_{name}/__init__.py": MODULE.format(name=name),
            f"tests/test_{name}.py": TEST.format(name=name),
            "canary.toml": CANARY.format(name=name),
            ".github/workflows/ci.yml": CI}


def write(name: str, folder: str | None = None) -> str:
    """Write the scaffold into `folder` (default ./ildbench-NAME), which must not exist or
    be empty; returns the folder."""
    check_name(name)
    folder = folder or f"ildbench-{name}"
    if os.path.exists(folder) and (not os.path.isdir(folder) or os.listdir(folder)):
        raise ScaffoldError(f"{folder} exists and is not an empty folder; pick another with "
                            "--dir or remove it")
    for rel, text in files(name).items():
        path = os.path.join(folder, rel)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            f.write(text)
    return folder
