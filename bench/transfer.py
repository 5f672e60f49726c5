"""Transfer evaluation: a final policy scored under changed test dynamics.

Normalization under a perturbation p uses references measured under the SAME p by the same
evaluator: (R_p - R_random,p) / (R_expert,p - R_random,p), with the deterministic expert and
uniform random actions on REFERENCE_EPISODES fixed episodes. At magnitude 0 the demo's own
nominal references are used, so a zero perturbation gives exactly the nominal score.
References are computed once per (demo, perturbation) and stored beside the demos, in the
package data `tasks/data/references/<task>.json` (committed: evaluations are deterministic on
CPU). Where the package folder is read-only (an installed wheel), new entries go to
`~/.cache/ildbench/references` and are read from there on top of the packaged ones.
"""
from __future__ import annotations

import json
import os

import numpy as np

from bench.api import Policy
from bench.evaluator import EvalConfig, Evaluator, random_policy
from bench.perturb import Perturbation, default_set, inapplicable, perturbed_task
from bench.store import write_json_atomic
from tasks.core import Task
from tasks.demo import Demo
from tasks.registry import DATA_DIR

REF_DIR = os.environ.get("ILDBENCH_REFERENCES", os.path.join(DATA_DIR, "references"))
USER_REF_DIR = os.path.join(os.path.expanduser("~"), ".cache", "ildbench", "references")


def _load(path: str) -> dict:
    try:
        with open(path) as f:
            return json.load(f)
    except (FileNotFoundError, json.JSONDecodeError):
        return {}


def load_references(name: str, ref_dir: str | None = None) -> dict:
    """The reference file `name` (e.g. "hopper.json"): the stored one, with entries this user
    added where the stored folder is read-only laid over it."""
    base = _load(os.path.join(ref_dir or REF_DIR, name))
    if ref_dir is None and not os.access(REF_DIR, os.W_OK):
        for key, entry in _load(os.path.join(USER_REF_DIR, name)).items():
            base[key] = {**base.get(key, {}), **entry} if isinstance(entry, dict) else entry
    return base


def store_reference(name: str, key: str, entry, subkey: str | None = None,
                    ref_dir: str | None = None) -> str:
    """Add `entry` under `key` (and `subkey`) to the reference file `name`, re-reading it first
    (another worker may have added entries meanwhile). Written beside the packaged references,
    or to the user's cache where that folder is read-only. Returns the path written."""
    for folder in ((ref_dir,) if ref_dir else (REF_DIR, USER_REF_DIR)):
        path = os.path.join(folder, name)
        cache = _load(path)
        if subkey is None:
            cache[key] = entry
        else:
            cache.setdefault(key, {})[subkey] = entry
        try:
            os.makedirs(folder, exist_ok=True)
            write_json_atomic(path, cache)
            return path
        except OSError:
            continue
    raise OSError(f"could not store reference {name!r} in {REF_DIR} or {USER_REF_DIR}")


def references(task: Task, demo: Demo, p: Perturbation) -> tuple[float, float]:
    """(R_expert, R_random) under perturbation p."""
    if p.magnitude == 0:
        return demo.expert_return, demo.random_return
    if task.spec.success_score:  # the score is the success rate under any dynamics
        return 1.0, 0.0
    from bench.expert import REFERENCE_EPISODES, REFERENCE_SEED, expert_policy
    entry = load_references(f"{task.name}.json").get(demo.sha256, {}).get(p.key)
    if entry is None:
        ev = Evaluator(perturbed_task(task, p),
                       EvalConfig(num_episodes=REFERENCE_EPISODES, deterministic=True))
        entry = {"expert": ev.evaluate(expert_policy(task.name), REFERENCE_SEED).mean_return,
                 "random": ev.evaluate(random_policy(task.action_size),
                                       REFERENCE_SEED).mean_return}
        store_reference(f"{task.name}.json", demo.sha256, entry, subkey=p.key)
    return entry["expert"], entry["random"]


def evaluate_transfer(task: Task, demo: Demo, policy: Policy, seed: int, config: EvalConfig,
                      perturbations, allow_sim_at_test: bool = False) -> dict[str, dict]:
    """{perturbation key: {family, magnitude, return, normalized, expert_return,
    random_return}} for the policy under each perturbation."""
    out = {}
    for p in perturbations:
        why = inapplicable(task, p)
        if why is not None:
            out[p.key] = {"family": p.family, "magnitude": p.magnitude, "skipped": why}
            continue
        r_exp, r_rand = references(task, demo, p)
        ev = Evaluator(perturbed_task(task, p), config, r_exp, r_rand, allow_sim_at_test)
        res = ev.evaluate(policy, seed)
        out[p.key] = {"family": p.family, "magnitude": p.magnitude,
                      "return": res.mean_return, "normalized": res.mean_normalized,
                      "length": res.mean_length, "expert_return": r_exp, "random_return": r_rand}
    return out


def transfer_summary(transfer: dict[str, dict], task: Task | None = None) -> float | None:
    """The leaderboard's 'transfer' number: mean normalized score over the families at their
    default magnitudes (magnitude-0 and skipped entries excluded; with `task`, also entries
    of families that cannot affect it, for records made before that rule)."""
    vals = [v["normalized"] for v in transfer.values()
            if v["magnitude"] != 0 and "skipped" not in v and not (
                task is not None and inapplicable(task, Perturbation(v["family"],
                                                                     v["magnitude"])))]
    return float(np.mean(vals)) if vals else None


def default_summary(transfer: dict[str, dict], task: Task | None = None) -> float | None:
    """transfer_summary over the entries at the task's default magnitudes (a robustness grid
    also holds other magnitudes). None when the record lacks one of them: it was scored under
    other defaults (e.g. before the task's calibration) and its mean would not be comparable."""
    if not transfer:
        return None
    keys = {p.key for p in default_set(task) if task is None or inapplicable(task, p) is None}
    if not keys <= set(transfer):
        return None
    return transfer_summary({k: v for k, v in transfer.items() if k in keys}, task)
