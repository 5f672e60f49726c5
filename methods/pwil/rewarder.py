"""PWIL's reward (Dadashi et al. 2021): a greedy, online Wasserstein coupling between the
agent's episode and the demo.

Expert atoms (standardized (s, a) or s) carry mass 1/N each; each agent step carries 1/T.
At every step the agent's mass is poured greedily into the closest expert atoms still holding
mass; the step's cost is sum(mass moved x distance) and its reward is
    r = alpha * exp(-beta * T / sqrt(d) * cost)       (alpha = beta = 5 in the paper).
Atoms' masses are restored at the start of every episode. Vectorized over parallel envs: for
each env, sorting the remaining atoms by distance and taking
min(atom mass, remaining step mass) along the cumulative sum is exactly the greedy loop.
"""
from __future__ import annotations

import numpy as np


class PWILRewarder:
    def __init__(self, expert_atoms: np.ndarray, num_envs: int, horizon: int,
                 alpha: float = 5.0, beta: float = 5.0, scale_floor: float = 0.2):
        atoms = np.asarray(expert_atoms, np.float64)
        if atoms.ndim != 2 or len(atoms) < 1:
            raise ValueError(f"expert atoms must be (N, d) with N >= 1, got {atoms.shape}")
        # Standardization (the original: sklearn StandardScaler fit on the demo atoms), with
        # each feature's scale floored at `scale_floor` (in the feature's own units): one
        # 128-step demo shows almost no spread in some features that differ between expert
        # episodes (reacher's fingertip-to-target offsets, std 0.012 within the demo), and a
        # raw 1/std there lets that one feature decide every distance. A floor of 0 is the
        # original's StandardScaler (zero-variance features get scale 1).
        if scale_floor < 0:
            raise ValueError(f"scale_floor must be >= 0, got {scale_floor}")
        self.mean = atoms.mean(0)
        std = atoms.std(0)
        self.scale = (np.maximum(std, scale_floor) if scale_floor > 0
                      else np.where(std < 1e-6, 1.0, std))
        self.atoms = (atoms - self.mean) / self.scale
        self.num_atoms, self.dim = self.atoms.shape
        self.num_envs = int(num_envs)
        self.horizon = int(horizon)
        self.alpha, self.beta = float(alpha), float(beta)
        self.sigma = self.beta * self.horizon / np.sqrt(self.dim)
        self.weights = np.empty((self.num_envs, self.num_atoms))
        self.reset()

    def reset(self, mask: np.ndarray | None = None) -> None:
        """Restore the expert mass (all envs, or those where `mask` is True)."""
        if mask is None:
            self.weights[:] = 1.0 / self.num_atoms
        else:
            self.weights[np.asarray(mask, bool)] = 1.0 / self.num_atoms

    def standardize(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, np.float64) - self.mean) / self.scale

    def step_costs(self, x: np.ndarray) -> np.ndarray:
        """Greedy transport cost of one agent step per env (x: (num_envs, d), raw features);
        removes the mass it used from the atoms."""
        z = self.standardize(x)
        dist = np.sqrt(((z[:, None, :] - self.atoms[None]) ** 2).sum(-1))      # (E, N)
        dist = np.where(self.weights > 0, dist, np.inf)
        order = np.argsort(dist, axis=1, kind="stable")
        w = np.take_along_axis(self.weights, order, 1)
        d = np.take_along_axis(dist, order, 1)
        before = np.cumsum(w, 1) - w
        moved = np.clip(1.0 / self.horizon - before, 0.0, w)
        cost = (moved * np.where(moved > 0, d, 0.0)).sum(1)
        np.put_along_axis(self.weights, order, w - moved, 1)
        self.weights[self.weights < 1e-12] = 0.0
        return cost

    def rewards(self, x: np.ndarray) -> np.ndarray:
        return self.alpha * np.exp(-self.sigma * self.step_costs(x))


def greedy_episode_cost(agent: np.ndarray, expert: np.ndarray) -> float:
    """Total greedy coupling cost of one agent episode (T, d) against expert atoms (N, d),
    in the rewarder's standardized units (horizon = T)."""
    r = PWILRewarder(expert, num_envs=1, horizon=len(agent))
    return float(sum(r.step_costs(a[None])[0] for a in agent))


def exact_episode_cost(agent: np.ndarray, expert: np.ndarray) -> float:
    """The exact optimal-transport (EMD) cost between the same weighted atoms, by POT."""
    import ot

    r = PWILRewarder(expert, num_envs=1, horizon=len(agent))
    za, ze = r.standardize(agent), r.atoms
    M = ot.dist(za, ze, metric="euclidean")
    return float(ot.emd2(np.full(len(za), 1.0 / len(za)), np.full(len(ze), 1.0 / len(ze)), M))
