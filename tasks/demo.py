"""The one-demo data format: validated, versioned expert trajectories.

Time convention (state t is BEFORE action t; the original code was off by one here):

    states[k, t]  matched state s_t, t = 0..T        (T + 1 rows; s_0 is the reset state)
    obs[k, t]     observation  o_t of s_t, t = 0..T  (T + 1 rows)
    actions[k, t] a_t, applied in s_t,  t = 0..T-1   (T rows)
    rewards[k, t] r_t for the transition s_t -a_t-> s_{t+1}

So (obs[t], actions[t]) is a correct BC pair, and a rollout's post-step states
s_1..s_T compare with states[1:] at equal t. A file holds K >= 1 trajectories of the same
task, best first: index 0 is "the" demo of the one-demo protocol; the others serve the
paper's multi-demo experiment (Appendix A.4).

A file is a .npz: the arrays above, `init_keys` (K, 2) uint32, the PRNG keys whose
`env.reset` gives each trajectory's initial state (exact: the brax version is checked),
`returns` (K,), and `meta`, a JSON string (see `Demo.meta`).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from typing import Any, Mapping

import numpy as np

FORMAT_VERSION = 1
_ARRAYS = ("obs", "states", "actions", "rewards", "init_keys", "returns")


class DemoError(ValueError):
    """A demo file that cannot be used; the message names the file, the field and the fix."""


@dataclasses.dataclass(frozen=True, eq=False)
class Demo:
    obs: np.ndarray
    """(K, T+1, obs_dim) float32: observations o_0..o_T."""
    states: np.ndarray
    """(K, T+1, state_dim) float32: matched states s_0..s_T."""
    actions: np.ndarray
    """(K, T, act_dim) float32: actions a_0..a_{T-1}, each in [-1, 1]."""
    rewards: np.ndarray
    """(K, T) float32: true rewards r_0..r_{T-1}."""
    init_keys: np.ndarray
    """(K, 2) uint32: env.reset(key) reproduces s_0 of each trajectory."""
    returns: np.ndarray
    """(K,) float32: sum of rewards of each trajectory."""
    meta: Mapping[str, Any]
    """format_version, task, backend, episode_length, versions {brax, jax, ildbench},
    expert {source, seed, ...}, reference {expert_return, random_return, num_episodes,
    eval_seed, deterministic}."""
    path: str = "<memory>"
    sha256: str = ""

    @property
    def num_demos(self) -> int:
        return int(self.actions.shape[0])

    @property
    def length(self) -> int:
        return int(self.actions.shape[1])

    @property
    def expert_return(self) -> float:
        return float(self.meta["reference"]["expert_return"])

    @property
    def random_return(self) -> float:
        return float(self.meta["reference"]["random_return"])

    def normalize(self, ret):
        """(R - R_random) / (R_expert - R_random), with both references from this demo."""
        return (np.asarray(ret) - self.random_return) / (self.expert_return - self.random_return)

    def top(self, k: int) -> "Demo":
        """The first k trajectories (best first)."""
        if not 1 <= k <= self.num_demos:
            raise DemoError(f"{self.path}: asked for {k} demos, file holds {self.num_demos}")
        cut = {f: getattr(self, f)[:k] for f in _ARRAYS}
        return dataclasses.replace(self, **cut)


def library_versions() -> dict[str, str]:
    import brax
    import jax

    return {"brax": brax.__version__, "jax": jax.__version__, "ildbench": harness_version()}


def harness_version() -> str:
    """The installed ildbench's version (the package metadata; "unknown" from a checkout
    that was never installed). tasks/ does not import bench/, where the version is written."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("ildbench")
    except PackageNotFoundError:
        return "unknown"


def save_demo(path: str, demo: Demo) -> str:
    """Write atomically; returns the file's sha256."""
    validate_arrays(demo, path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp.npz"
    np.savez_compressed(tmp, meta=np.array(json.dumps(dict(demo.meta), sort_keys=True)),
                        **{f: getattr(demo, f) for f in _ARRAYS})
    os.replace(tmp, path)
    return file_sha256(path)


def file_sha256(path: str) -> str:
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def _fail(path, field, problem, fix):
    raise DemoError(f"demo {path}: field {field!r} {problem}. Fix: {fix}")


def validate_arrays(demo: Demo, path: str) -> None:
    """Shapes, dtypes, finiteness and internal consistency; no task needed."""
    regen = "regenerate it with `ildbench expert demo --task <task>`"
    want = {"obs": 3, "states": 3, "actions": 3, "rewards": 2, "init_keys": 2, "returns": 1}
    for f, nd in want.items():
        a = getattr(demo, f)
        if not isinstance(a, np.ndarray) or a.ndim != nd:
            _fail(path, f, f"must be a {nd}-d array, got shape {getattr(a, 'shape', None)}", regen)
        if f == "init_keys":
            if a.dtype != np.uint32 or a.shape[1] != 2:
                _fail(path, f, f"must be uint32 (K, 2), got {a.dtype} {a.shape}", regen)
        elif a.dtype != np.float32:
            _fail(path, f, f"must be float32, got {a.dtype}", regen)
        elif not np.isfinite(a).all():
            _fail(path, f, f"has {int((~np.isfinite(a)).sum())} non-finite values", regen)
    k, t = demo.actions.shape[:2]
    if k < 1 or t < 1:
        _fail(path, "actions", f"is empty (shape {demo.actions.shape})", regen)
    expect = {"obs": (k, t + 1), "states": (k, t + 1), "rewards": (k, t),
              "init_keys": (k,), "returns": (k,)}
    for f, lead in expect.items():
        got = getattr(demo, f).shape[: len(lead)]
        if got != lead:
            _fail(path, f, f"has leading shape {got}, expected {lead} (K={k} demos of "
                           f"T={t} actions; obs/states hold T+1 rows, s_0..s_T)", regen)
    if np.abs(demo.actions).max() > 1.0 + 1e-6:
        _fail(path, "actions", "has values outside [-1, 1]", regen)
    if not np.allclose(demo.rewards.sum(1), demo.returns, rtol=1e-4, atol=1e-3):
        _fail(path, "returns", "does not equal the sum of rewards", regen)
    meta = demo.meta
    for key in ("format_version", "task", "backend", "episode_length", "versions", "expert",
                "reference"):
        if key not in meta:
            _fail(path, f"meta.{key}", "is missing", regen)
    for key in ("expert_return", "random_return"):
        v = meta["reference"].get(key)
        if not isinstance(v, (int, float)) or not np.isfinite(v):
            _fail(path, f"meta.reference.{key}", f"must be a finite number, got {v!r}", regen)
    if not meta["reference"]["expert_return"] > meta["reference"]["random_return"]:
        _fail(path, "meta.reference", "has expert_return <= random_return, so scores cannot "
              "be normalized", "train a better expert, then regenerate the demo")


def load_demo(path: str, task=None) -> Demo:
    """Load and validate a demo file; with `task` (a tasks.Task), also check it matches."""
    if not os.path.exists(path):
        raise DemoError(f"demo {path}: file not found. Fix: create it with "
                        "`ildbench expert demo --task <task>` or fix the task's demo entry")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [f for f in (*_ARRAYS, "meta") if f not in z.files]
            if missing:
                _fail(path, missing[0], "is missing from the file",
                      "regenerate it with `ildbench expert demo --task <task>`")
            arrays = {f: z[f] for f in _ARRAYS}
            meta = json.loads(str(z["meta"]))
    except DemoError:
        raise
    except Exception as e:  # not an npz, truncated, bad JSON ...
        raise DemoError(f"demo {path}: cannot be read as a demo file ({type(e).__name__}: {e})."
                        " Fix: regenerate it with `ildbench expert demo --task <task>`") from e
    demo = Demo(**arrays, meta=meta, path=path, sha256=file_sha256(path))
    validate_arrays(demo, path)
    if meta["format_version"] != FORMAT_VERSION:
        _fail(path, "meta.format_version", f"is {meta['format_version']}, this ildbench reads "
              f"{FORMAT_VERSION}", "regenerate the demo with this version")
    if task is not None:
        check_matches_task(demo, task)
    return demo


def check_matches_task(demo: Demo, task) -> None:
    path, meta = demo.path, demo.meta
    fix = f"regenerate it with `ildbench expert demo --task {task.name}`"
    if meta["task"] != task.name:
        _fail(path, "meta.task", f"is {meta['task']!r} but the task is {task.name!r}",
              "point the task at its own demo file")
    if meta["backend"] != task.spec.backend:
        _fail(path, "meta.backend", f"is {meta['backend']!r} but task {task.name!r} pins "
              f"{task.spec.backend!r}", fix)
    if demo.length != task.episode_length or meta["episode_length"] != task.episode_length:
        _fail(path, "actions", f"holds {demo.length} steps, task {task.name!r} runs "
              f"{task.episode_length}", fix)
    for f, size in (("obs", task.obs_size), ("states", task.state_size),
                    ("actions", task.action_size)):
        if getattr(demo, f).shape[2] != size:
            _fail(path, f, f"has width {getattr(demo, f).shape[2]}, task {task.name!r} has "
                  f"{size}", fix)
    import brax  # physics results depend on the brax version: a demo from another is stale
    if meta["versions"].get("brax") != brax.__version__:
        _fail(path, "meta.versions.brax", f"is {meta['versions'].get('brax')!r}, installed "
              f"brax is {brax.__version__!r}", fix + " (or install the demo's brax version)")
