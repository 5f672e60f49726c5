"""Does PWIL's reward rank policies the way the task's reward does? A probe without training.

    python -m benchmarks.pwil_probe --tasks hopper ant humanoid [--episodes 16]
        [--noise 0 0.3 0.6 1.0] [--out results/probes/pwil_reward.csv]

PWIL's learner maximizes the discounted sum of PWIL rewards over an episode that ends at
termination, so what it is pulled towards is each policy's PWIL return: the sum of the
greedy-coupling rewards (methods/pwil/rewarder.py, with the task's PWIL config and the
demo's first episode as the expert atoms, exactly as a run sees them) over the steps before
termination. The probe rolls, from the same initial states, a ladder of policies whose task
score is known to fall: the expert with Gaussian action noise of each `--noise` std (clipped
to [-1, 1]), all-zero actions, and uniform random actions. For each it prints the
normalized task score (the demo's references, rewards after the first termination masked as
the shared evaluator does), the mean episode length, the PWIL return and PWIL's mean reward
per step alive, and across all episodes the rank correlation (Spearman) of PWIL return with
task return.

Where the ladder's PWIL returns fall with its task scores, the reward points the right way
and a learner that stays low is short of samples or updates; where a policy that scores
lower on the task earns as much PWIL return (a policy that stands still against one that
moves badly), the reward itself does not ask for what the task scores.
"""
from __future__ import annotations

import argparse
import csv
import os

import jax
import numpy as np


def alive_mask(dones: np.ndarray) -> np.ndarray:
    """(N, T) 1 for the steps before termination, the terminating step included: step t
    counts while no step before it was done (the shared evaluator's masking)."""
    dones = np.asarray(dones, bool)
    before = np.concatenate([np.zeros_like(dones[:, :1]), dones[:, :-1]], axis=1)
    return (np.cumsum(before, axis=1) == 0).astype(np.float64)


def pwil_rewards(rewarder_args: dict, use_actions: bool, obs: np.ndarray,
                 actions: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """(N, T) PWIL's reward of each step of N episodes, one coupling per episode (the atoms'
    mass restored at its start), 0 after termination; the features as the run builds them."""
    from methods.pwil.rewarder import PWILRewarder
    from methods.pwil.train import features
    n, T = actions.shape[:2]
    r = PWILRewarder(num_envs=n, **rewarder_args)
    out = np.stack([r.rewards(features(obs[:, t], actions[:, t], use_actions))
                    for t in range(T)], axis=1)
    return out * alive


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    from scipy.stats import spearmanr
    return float(spearmanr(x, y).statistic)


def noisy(policy, noise: float):
    """`policy` (a stateless bench.api Policy, acting deterministically) with Gaussian action
    noise of std `noise`; `bench.expert.rollout` clips the sum to [-1, 1]."""
    from bench.api import Policy

    def act(params, obs, key, deterministic):
        k_act, k_noise = jax.random.split(key)
        a = policy.act(params, obs, k_act, True)
        return a + noise * jax.random.normal(k_noise, a.shape)
    return Policy(act=act, params=policy.params)


def probe(task_name: str, episodes: int = 16, noise=(0.0, 0.3, 0.6, 1.0),
          seed: int = 0) -> tuple[list[dict], float]:
    """(one row per policy, Spearman rho of PWIL return with task return over all
    episodes)."""
    from bench.evaluator import random_policy
    from bench.expert import expert_policy, rollout
    from bench.floors import zero_action_policy
    from bench.plugins import build_config, get_method
    from methods.pwil.train import expert_atoms
    from tasks import make_task
    from tasks.demo import load_demo

    task = make_task(task_name)
    demo = load_demo(task.spec.demo_path, task)
    cfg = build_config(get_method("pwil"), task_name, "cpu")
    atoms, _, _ = expert_atoms(demo, cfg)
    args = dict(expert_atoms=atoms, horizon=cfg.horizon, alpha=cfg.alpha, beta=cfg.beta,
                scale_floor=cfg.scale_floor)
    expert = expert_policy(task_name)
    if expert.init_memory is not None:
        raise ValueError(f"task {task_name!r}: its expert is open loop; the probe needs a "
                         "feedback expert (a PPO or SAC policy)")
    ladder = [(f"expert, noise {s:g}", expert, s) for s in noise]
    ladder += [("zero_action", zero_action_policy(task.action_size), 0.0),
               ("random", random_policy(task.action_size), 0.0)]
    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    span = demo.expert_return - demo.random_return
    rows, task_ret, pwil_ret = [], [], []
    for name, pol, s in ladder:
        r = rollout(task, noisy(pol, s), keys)
        obs, actions = r["obs"][:, :-1], r["actions"]  # obs: s_0..s_T
        rewards, dones = r["rewards"], r["dones"]
        alive = alive_mask(dones)
        ret = (rewards * alive).sum(1)
        pw = pwil_rewards(args, cfg.use_actions, obs, actions, alive)
        task_ret.append(ret)
        pwil_ret.append(pw.sum(1))
        rows.append({"task": task_name, "policy": name,
                     "normalized": float(np.mean((ret - demo.random_return) / span)),
                     "length": float(alive.sum(1).mean()),
                     "pwil_return": float(pw.sum(1).mean()),
                     "pwil_per_step": float(pw.sum() / alive.sum()),
                     "episodes": episodes})
    rho = spearman(np.concatenate(task_ret), np.concatenate(pwil_ret))
    for row in rows:
        row["spearman_all"] = rho
    return rows, rho


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", nargs="+", default=["hopper", "ant", "humanoid"])
    p.add_argument("--episodes", type=int, default=16)
    p.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.3, 0.6, 1.0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="CSV to write (one row per task x policy)")
    a = p.parse_args(argv)
    out = []
    for t in a.tasks:
        rows, rho = probe(t, a.episodes, a.noise, a.seed)
        out += rows
        print(f"\n{t}: Spearman rho of PWIL return with task return over "
              f"{a.episodes * len(rows)} episodes = {rho:.3f}")
        print(f"{'policy':<20}{'normalized':>11}{'length':>8}{'PWIL return':>13}"
              f"{'PWIL/step':>11}")
        for r in rows:
            print(f"{r['policy']:<20}{r['normalized']:>11.3f}{r['length']:>8.1f}"
                  f"{r['pwil_return']:>13.2f}{r['pwil_per_step']:>11.3f}")
    if a.out:
        os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
        with open(a.out, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(out[0]))
            w.writeheader()
            w.writerows(out)
        print(f"\nwritten: {a.out}")


if __name__ == "__main__":
    main()
