"""A minimal differentiable mass-spring cloth in JAX: exactly what the hanging scene needs.

Modelled (facts: shared/reference/cloth_facts.md, the ILD release's engine):
  - 288 unit-mass particles on a 12 x 24 grid, spacing c = 1/64;
  - 8-neighbour springs (structural + shear), Hookean on strain: F = k (l - l0)/l0 along the
    link, k = 1600, counted from both ends; no bending springs, no dashpots;
  - gravity 0.5 along -y (y is up), velocity damping exp(-2 dt) per substep;
  - the pole: an infinite cylinder along x at (y, z) = (0.3, 0.15), r = 0.01; a particle in
    contact loses its inward normal velocity and is slowed x0.95 (velocity-only response);
  - two kinematic "sticky" grippers (spheres, r = 0.01): each substep, particles inside a
    sphere move with it and get zero velocity;
  - the unit box [0, 1]^3 as ground/walls (a position clamp, velocity untouched) and a
    +/-2 velocity clip; while any velocity component exceeds max_v the grippers do not move
    (the original's guard);
  - semi-implicit Euler, dt = 2e-3, 50 substeps per action (0.1 s).

Not modelled (not needed for the scene: see the facts): bending, self-collision, ground
friction, gripper collisions, rendering.

Substep order (as the original): gravity, springs, damping, pole, grippers (attach + move),
gripper positions += displacement and clip to the box, x clip, v clip, x += dt v.

Speed/memory: links are the 8 precomputed directions on the (12, 24) grid, read by shifted
slices (no gather, no scatter in the gradient; `neighbours()` is the same links as a table,
the tests' reference); the substeps of one action are a lax.scan wrapped in jax.checkpoint, so reverse mode stores
one state per action step, not 50 x 80 substep states. With `grad_norm` the original's
stabilizer runs after every substep and gripper interaction: an identity whose cotangent is
replaced by nan_to_num(g / ||g||) / 288 per array (per example under vmap).

Stability: explicit integration of stiff springs is stable only for dt < 2 / omega_max,
omega_max^2 the largest eigenvalue of the spring stiffness matrix at rest (unit masses).
`stability_limit` computes it (~2.3e-3 s here); `check_stable` refuses a larger dt with an
error naming the limit, and `max_strain` reports a blown-up state instead of letting NaNs
propagate silently.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.experimental
import jax.numpy as jnp
import numpy as np

ROWS, COLS = 12, 24
N = ROWS * COLS  # 288 particles
SPACING = 1.0 / 64.0
GRID0 = (24, 24)  # (row, col) offset of the cloth in the original 64 x 64 index grid
POLE_YZ = (0.3, 0.15)
POLE_RADIUS = 0.01
GRIPPER_RADIUS = 0.01
ACTION_STEP = 0.05  # gripper displacement per action step per unit action (the original:
#                     1e-3 per substep x 50 substeps; spread over the substeps whatever dt)
# The grippers' start: the settled positions of particles 53 (row 2, col 5) and 245
# (row 10, col 5), hard-coded as in the original.
GRIPPER_START = ((0.40625, -0.0005, 0.51645), (0.53125, -0.0005, 0.51644))
GRIPPER_PARK = (0.0, 0.1, 0.58)  # where the grippers wait while the cloth settles
SETTLE_STEPS = 60


class InstabilityError(RuntimeError):
    """The integrator is outside its stability region (or a state blew up)."""


@dataclasses.dataclass(frozen=True)
class ClothParams:
    dt: float = 2e-3
    substeps: int = 50
    stiffness: float = 1600.0
    damping: float = 2.0
    gravity: float = 0.5
    max_v: float = 2.0
    pole_friction: float = 0.95
    grad_norm: bool = True
    """The original's per-substep gradient normalization (see module doc)."""

    @property
    def action_time(self) -> float:
        return self.dt * self.substeps


class ClothState(NamedTuple):
    x: jax.Array      # (288, 3) positions
    v: jax.Array      # (288, 3) velocities
    grip: jax.Array   # (2, 4) gripper (x, y, z, r)


# The 8 link directions (row, column offsets): structural and shear.
_OFFSETS = tuple((di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0))


@functools.lru_cache(maxsize=None)
def neighbours() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(idx (288, 8) int32, mask (288, 8) bool, rest (288, 8) float32): each particle's 8
    neighbours (structural and shear) in row-major particle order; missing ones masked and
    pointing at the particle itself. The simulator reads links by slices (`_links`); this
    table is the independent reference the tests check it against."""
    idx = np.zeros((N, 8), np.int32)
    mask = np.zeros((N, 8), bool)
    rest = np.ones((N, 8), np.float32)
    for i in range(ROWS):
        for j in range(COLS):
            p = i * COLS + j
            for k, (di, dj) in enumerate(_OFFSETS):
                a, b = i + di, j + dj
                ok = 0 <= a < ROWS and 0 <= b < COLS
                idx[p, k] = a * COLS + b if ok else p
                mask[p, k] = ok
                rest[p, k] = SPACING * np.sqrt(di * di + dj * dj)
    return idx, mask, rest


def initial_layout() -> np.ndarray:
    """(288, 3): the original's 45-degree incline, before settling."""
    i = np.arange(GRID0[0], GRID0[0] + ROWS)[:, None] * np.ones((1, COLS))
    j = np.ones((ROWS, 1)) * np.arange(GRID0[1], GRID0[1] + COLS)[None, :]
    c = SPACING
    x = np.stack([i * c, j * c / np.sqrt(2), (64 - j) * c / np.sqrt(2) + 0.1], -1)
    return x.reshape(N, 3).astype(np.float32)


# --- per-substep gradient normalization (the original's stabilizer) --------------------
@jax.custom_vjp
def _gn(x):
    return x


def _gn_fwd(x):
    return x, None


def _gn_bwd(_, g):
    n = jnp.sqrt(jnp.sum(g * g))
    return (jnp.nan_to_num(g / n) / N,)


_gn.defvjp(_gn_fwd, _gn_bwd)


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def spring_forces(x: jax.Array, stiffness: float) -> jax.Array:
    """(288, 3) spring forces F = -dE/dx of the spring energy.

    Forward: on the (12, 24) grid, one shifted slice per link direction (faster than
    gathering the neighbour table, whose gradient is a scatter-add). Backward: the Jacobian
    dF/dx = -Hessian(E) is symmetric, so the vector-Jacobian product g^T J equals the
    Jacobian-vector product J g: one forward-mode pass, several times cheaper on a CPU than
    reverse mode through the slices (tests/test_cloth.py checks the two agree)."""
    return _spring_forces(x, stiffness)


def _forces_fwd(x, stiffness):
    return _spring_forces(x, stiffness), x


def _forces_bwd(stiffness, x, g):
    return (jax.jvp(lambda y: _spring_forces(y, stiffness), (x,), (g,))[1],)


spring_forces.defvjp(_forces_fwd, _forces_bwd)


def _links(x: jax.Array):
    """Per link direction: (d (12, 24, 3) neighbour minus particle, valid (12, 24) mask of
    links inside the cloth, rest length), by shifted slices of the padded grid."""
    g = x.reshape(ROWS, COLS, 3)
    pad = jnp.pad(g, ((1, 1), (1, 1), (0, 0)))
    for di, dj in _OFFSETS:
        valid = np.zeros((ROWS, COLS), bool)
        valid[max(0, -di):ROWS - max(0, di), max(0, -dj):COLS - max(0, dj)] = True
        yield (pad[1 + di:1 + di + ROWS, 1 + dj:1 + dj + COLS] - g, valid,
               SPACING * np.sqrt(di * di + dj * dj))


def _spring_forces(x: jax.Array, stiffness: float) -> jax.Array:
    f = jnp.zeros((ROWS, COLS, 3), x.dtype)
    for d, valid, rest in _links(x):
        sq = jnp.sum(d * d, -1)
        ok = valid & (sq > 0)
        length = jnp.sqrt(jnp.where(ok, sq, 1.0))  # safe at zero length
        mag = jnp.where(ok, stiffness * (length - rest) / (rest * length), 0.0)
        f = f + mag[..., None] * d
    return f.reshape(N, 3)


def max_strain(x: jax.Array) -> jax.Array:
    """Largest link length / rest length (1 at rest; the unstable cloth reached 1.6-1.8)."""
    return jnp.max(jnp.stack([jnp.max(jnp.where(valid, jnp.linalg.norm(d, axis=-1) / rest, 0.0))
                              for d, valid, rest in _links(x)]))


def substep(p: ClothParams, s: ClothState, disp: jax.Array) -> ClothState:
    """One semi-implicit Euler substep. disp (2, 3): each gripper's displacement."""
    gn = _gn if p.grad_norm else (lambda a: a)
    x, v, grip = s
    dt = p.dt
    v = v.at[:, 1].add(-p.gravity * dt)
    v = v + spring_forces(x, p.stiffness) * dt
    v = v * np.exp(-p.damping * dt)
    # pole: remove the inward normal velocity of particles touching it, then "friction"
    dy, dz = x[:, 1] - POLE_YZ[0], x[:, 2] - POLE_YZ[1]
    r2 = dy * dy + dz * dz
    contact = r2 <= POLE_RADIUS ** 2
    r = jnp.sqrt(jnp.where(r2 > 0, r2, 1.0))
    ny, nz = dy / r, dz / r
    vn = jnp.minimum(v[:, 1] * ny + v[:, 2] * nz, 0.0)
    v_pole = jnp.stack([v[:, 0], v[:, 1] - vn * ny, v[:, 2] - vn * nz], -1) * p.pole_friction
    v = jnp.where(contact[:, None], v_pole, v)
    # grippers: skipped in a substep where any velocity component exceeds max_v
    moving = jnp.all(jnp.abs(v) <= p.max_v)
    for g in range(2):
        near = jnp.sum((x - grip[g, :3]) ** 2, -1) <= grip[g, 3] ** 2
        hold = (near & moving)[:, None]
        x = gn(jnp.where(hold, x + disp[g], x))
        v = gn(jnp.where(hold, 0.0, v))
    grip_xyz = jnp.where(moving, grip[:, :3] + disp, grip[:, :3])
    grip = jnp.concatenate([jnp.clip(grip_xyz, 0.0, 1.0), grip[:, 3:]], -1)
    x = jnp.clip(x, 0.0, 1.0)
    v = jnp.clip(v, -p.max_v, p.max_v)
    x = x + dt * v
    return ClothState(gn(x), gn(v), gn(grip))


def action_units(action: jax.Array) -> jax.Array:
    """(8,) action [dx0, dy0, dz0, suction0, dx1, dy1, dz1, suction1] -> (2, 3) gripper
    velocities clipped to [-1, 1]. The suction entries are ignored (the original forced
    them to 0)."""
    return jnp.clip(action, -1.0, 1.0).reshape(2, 4)[:, :3]


def substep_displacement(units: jax.Array, substeps: int = 50) -> jax.Array:
    """Gripper velocities in action units -> displacement per substep (ACTION_STEP per
    action step in all, whatever the substep count)."""
    return units * (ACTION_STEP / substeps)


def action_displacement(action: jax.Array, substeps: int = 50) -> jax.Array:
    """(8,) action -> (2, 3) gripper displacement per substep."""
    return substep_displacement(action_units(action), substeps)


def make_step(p: ClothParams):
    """step(state, disp (2, 3)) -> state after one action (p.substeps substeps), with the
    substeps rematerialized in the backward pass."""

    @jax.checkpoint
    def step(s: ClothState, disp: jax.Array) -> ClothState:
        return jax.lax.scan(lambda c, _: (substep(p, c, disp), None), s, None,
                            length=p.substeps)[0]

    return step


@functools.lru_cache(maxsize=None)
def settled_state(p: ClothParams = ClothParams()) -> ClothState:
    """The reset state: the incline after SETTLE_STEPS zero-action steps with the grippers
    parked away, then the grippers placed on particles 53 and 245 (deterministic; computed
    once per process, in float32, also when first asked for under jax's x64 mode)."""
    with jax.experimental.disable_x64():  # cached: the same float32 state in any mode
        return _settle(p)


def _settle(p: ClothParams) -> ClothState:
    park = jnp.asarray([[*GRIPPER_PARK, GRIPPER_RADIUS]] * 2, jnp.float32)
    s = ClothState(jnp.asarray(initial_layout()), jnp.zeros((N, 3), jnp.float32), park)
    step = make_step(dataclasses.replace(p, grad_norm=False))
    s = jax.jit(lambda s: jax.lax.scan(lambda c, _: (step(c, jnp.zeros((2, 3))), None), s,
                                       None, length=SETTLE_STEPS)[0])(s)
    start = jnp.asarray([[*g, GRIPPER_RADIUS] for g in GRIPPER_START], jnp.float32)
    s = jax.device_get(s._replace(grip=start))
    return ClothState(*(np.asarray(a) for a in s))


@functools.lru_cache(maxsize=None)
def stability_limit(stiffness: float = 1600.0) -> float:
    """Largest stable dt of the undamped explicit integrator at rest: 2 / omega_max, with
    omega_max^2 the largest eigenvalue of the stiffness matrix -dF/dx of the flat cloth at
    rest lengths (unit masses). Semi-implicit Euler on x'' = -K x is stable iff
    dt^2 lambda_max(K) < 4."""
    x0 = np.stack([np.repeat(np.arange(ROWS), COLS) * SPACING,
                   np.zeros(N), np.tile(np.arange(COLS), ROWS) * SPACING], -1)
    jac = jax.jacfwd(lambda x: _spring_forces(x.reshape(N, 3), stiffness).ravel())(
        jnp.asarray(x0.ravel(), jnp.float32))
    lam = float(np.linalg.eigvalsh(-np.asarray(jac, np.float64)).max())
    return 2.0 / np.sqrt(lam)


def check_stable(p: ClothParams) -> None:
    limit = stability_limit(p.stiffness)
    if p.dt >= limit:
        raise InstabilityError(
            f"cloth dt={p.dt:g} s is above the explicit integrator's stability limit "
            f"{limit:.3g} s for stiffness {p.stiffness:g} (the cloth would blow up while "
            f"settling). Fix: use dt < {limit:.3g} (more substeps per action: substeps >= "
            f"{int(np.ceil(p.action_time / limit))} for {p.action_time:g} s per action)")
