"""The cloth-hanging task (paper Section 4.2, Appendix B) as a brax Env over tasks/cloth/sim.

Episode: 80 actions of 0.1 s from the settled cloth (deterministic reset). Action (8,), the
original layout: [dx0, dy0, dz0, suction0, dx1, dy1, dz1, suction1], each velocity entry
clipped to [-1, 1] and moving its gripper by 0.05 per action; the suction entries are
ignored (the original forced them to 0), kept so the original expert files replay as is.

Observation = matched state (1736 numbers, the original layout): per particle
(x, y, z, vx, vy, vz) interleaved, 288 x 6 = 1728, then gripper 0 (x, y, z, r) and gripper 1
(x, y, z, r). Two entries are the constant radii.

Success (the original criterion, on the cloth after the last action): max y >= 0.3 (the pole
axis height), min z <= 0.15 and max z >= 0.15 (the cloth spans both sides of the pole).
Reward = success at the last step, 0 before, so the return is 0 or 1 and the normalized
score (R_expert = 1, R_random = 0) is the success rate.

Test dynamics (`noise` > 0 / `bias` > 0; the demo and training use neither): each action
step, a uniform +/-`noise` (action units; the original: 0.05) is added to every gripper
velocity entry, plus a fixed bias drawn per episode uniformly in +/-`bias` (the original:
0.2), both after the [-1, 1] clip, as the original added them to the displacement. The
original drew its bias once from PRNGKey(1) and reused one noise sequence for every
episode and iteration; here both come from the episode's reset key (`noise_info`): every
evaluation episode has its own bias and noise, and an evaluation (fixed keys) is
reproducible. A perturbation in fixed mode (bench.perturb) draws them from one constant key
for every episode instead, the original's setting.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State

from tasks.cloth import sim

EPISODE_LENGTH = 80
TEST_NOISE, TEST_BIAS = 0.05, 0.2  # the original test env's magnitudes, in action units
POLE_HEIGHT, POLE_Z = sim.POLE_YZ


def success(x: jax.Array) -> jax.Array:
    """1.0 if the cloth positions x (288, 3) hang on the pole, else 0.0."""
    y, z = x[:, 1], x[:, 2]
    ok = (jnp.max(y) >= POLE_HEIGHT) & (jnp.min(z) <= POLE_Z) & (jnp.max(z) >= POLE_Z)
    return ok.astype(jnp.float32)


def expert_actions() -> np.ndarray:
    """(80, 8) the original's hand-crafted expert (both grippers alike): lift (dy = +0.4)
    for 20 steps, carry over the pole (dz = -0.225) for 40, lower (dy = -0.1) for 20."""
    a = np.zeros((EPISODE_LENGTH, 8), np.float32)
    for g in (0, 4):
        a[:20, g + 1] = 0.4
        a[20:60, g + 2] = -0.225
        a[60:, g + 1] = -0.1
    return a


class ClothHang(Env):
    def __init__(self, dt: float = 2e-3, substeps: int = 50, noise: float = 0.0,
                 bias: float = 0.0, grad_norm: bool = True, check_stability: bool = True):
        self.params = sim.ClothParams(dt=dt, substeps=substeps, grad_norm=grad_norm)
        if check_stability:
            sim.check_stable(self.params)
        if noise < 0 or bias < 0:
            raise ValueError(f"cloth noise and bias must be >= 0, got {noise}, {bias}")
        self.noise, self.bias = float(noise), float(bias)
        self._step = sim.make_step(self.params)
        # The start state is settled once, eagerly, with the reference physics (a reset
        # traced inside jit then only embeds it as a constant).
        self._s0 = sim.settled_state(sim.ClothParams())
        self.episode_length = EPISODE_LENGTH

    def noise_info(self, key: jax.Array) -> dict:
        """The state info an episode's test noise comes from: its noise key and its bias
        (uniform in +/-`bias` per gripper velocity entry), drawn from `key`."""
        k_noise, k_bias = jax.random.split(key)
        return {"noise_key": k_noise,
                "bias": self.bias * jax.random.uniform(k_bias, (2, 3), minval=-1.0, maxval=1.0)}

    def reset(self, rng: jax.Array) -> State:
        s0 = self._s0
        ps = {"x": jnp.asarray(s0.x), "v": jnp.asarray(s0.v), "grip": jnp.asarray(s0.grip),
              "t": jnp.zeros(())}
        zero = jnp.zeros(())
        return State(pipeline_state=ps, obs=self.matched_state(ps), reward=zero, done=zero,
                     metrics={"max_strain": sim.max_strain(ps["x"])},
                     info=self.noise_info(rng))

    def step(self, state: State, action: jax.Array) -> State:
        ps = state.pipeline_state
        disp_units = sim.action_units(action)
        key = state.info["noise_key"]
        if self.noise > 0:
            key, k = jax.random.split(key)
            disp_units = disp_units + self.noise * jax.random.uniform(
                k, (2, 3), minval=-1.0, maxval=1.0)
        disp_units = disp_units + state.info["bias"]
        s = self._step(sim.ClothState(ps["x"], ps["v"], ps["grip"]),
                       sim.substep_displacement(disp_units, self.params.substeps))
        t = ps["t"] + 1.0
        ps2 = {"x": s.x, "v": s.v, "grip": s.grip, "t": t}
        reward = jnp.where(t >= self.episode_length, success(s.x), 0.0)
        return state.replace(pipeline_state=ps2, obs=self.matched_state(ps2), reward=reward,
                             done=jnp.zeros_like(state.done),
                             metrics={"max_strain": sim.max_strain(s.x)},
                             info={"noise_key": key, "bias": state.info["bias"]})

    def matched_state(self, ps: dict) -> jax.Array:
        return jnp.concatenate([jnp.concatenate([ps["x"], ps["v"]], -1).ravel(),
                                ps["grip"].ravel()])

    @property
    def observation_size(self) -> int:
        return sim.N * 6 + 8

    @property
    def action_size(self) -> int:
        return 8

    @property
    def backend(self) -> str:
        return "cloth"
