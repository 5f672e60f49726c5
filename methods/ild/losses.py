"""ILD's losses as pure functions (paper Eq. 1-3), plus the per-step gradient normalizer.

Chamfer-alpha between a rollout X = (s_1..s_T) and a demo Y = (g_1..g_M), both normalized:

    deviation  L_d = 1/T  sum_t min_m d(s_t, g_m)     (each rollout state to its nearest goal)
    coverage   L_g = 1/M  sum_m min_t d(s_t, g_m)     (each demo state covered by the rollout)
    L = L_g + alpha * L_d

alpha multiplies the deviation term, as Eq. 3, Algorithm 1 and the original code do (the
sentence "L_d + alpha L_g" in Section 3.2 contradicts them). d is either

    'sq'  : ||x - y||^2                 (the paper's text)
    'rms' : sqrt(mean_D (x - y)^2)      (the original code, which produced the paper's tables)
    'msq' : mean_D (x - y)^2            (the original code's cloth loss)

The default is 'rms': it is what produced the reported numbers, its value and gradient
do not grow with the state dimension D (52..143 here), and its gradient w.r.t. a state has
unit scale whatever the distance, so far goals do not dominate near ones. The square root
is made safe at zero distance: d = 0 gives gradient 0, never NaN (rollout == demo exactly).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class LossTerms(NamedTuple):
    loss: jax.Array
    coverage: jax.Array
    deviation: jax.Array


def safe_sqrt(x: jax.Array) -> jax.Array:
    """sqrt with gradient 0 (not inf/NaN) at 0: the double-where trick."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def _point_distance(sq: jax.Array, dim: int, distance: str) -> jax.Array:
    if distance == "sq":
        return sq
    if distance == "rms":
        return safe_sqrt(sq / dim)
    if distance == "msq":
        return sq / dim
    raise ValueError(f"distance must be 'rms', 'sq' or 'msq', got {distance!r}")


def nearest(x: jax.Array, y: jax.Array, mask: jax.Array | None = None):
    """Indices of nearest neighbours, (T,) into y and (M,) into x, without gradient.
    Uses ||x||^2 + ||y||^2 - 2 x.y: a (T, M) matmul, never a (T, M, D) tensor, so memory
    stays B x T x M at the paper's batch. Its cancellation error near zero distance can
    only swap near-equal neighbours; distances themselves are recomputed exactly.
    mask (T,) excludes rollout states (after termination) from being anyone's neighbour."""
    x, y = jax.lax.stop_gradient(x), jax.lax.stop_gradient(y)
    sq = (jnp.sum(x * x, -1)[:, None] + jnp.sum(y * y, -1)[None, :] - 2.0 * x @ y.T)
    to_x = jnp.argmin(sq if mask is None else jnp.where(mask[:, None], sq, jnp.inf), axis=0)
    return jnp.argmin(sq, axis=1), to_x


def pairwise_distance(x: jax.Array, y: jax.Array, distance: str = "rms") -> jax.Array:
    """(T, D), (M, D) -> (T, M) exact distances (for tests and diagnostics; O(T M D))."""
    sq = jnp.sum((x[:, None, :] - y[None, :, :]) ** 2, axis=-1)
    return _point_distance(sq, x.shape[-1], distance)


def _masked_mean(v: jax.Array, mask: jax.Array | None) -> jax.Array:
    if mask is None:
        return jnp.mean(v)
    w = mask.astype(v.dtype)
    return jnp.sum(w * v) / jnp.maximum(jnp.sum(w), 1.0)


def chamfer_alpha(x: jax.Array, y: jax.Array, alpha: float = 1.0, distance: str = "rms",
                  mask: jax.Array | None = None) -> LossTerms:
    """Chamfer-alpha between one rollout x (T, D) and one demo y (M, D).
    The gradient of a min is the gradient at its argmin, so distances are computed exactly
    (from differences) only for the nearest pairs. `mask` (T,) marks the rollout states
    that exist (False after termination): they neither deviate nor cover."""
    to_y, to_x = nearest(x, y, mask)
    dim = x.shape[-1]
    dev = _point_distance(jnp.sum((x - y[to_y]) ** 2, -1), dim, distance)
    deviation = _masked_mean(dev, mask)
    coverage = jnp.mean(_point_distance(jnp.sum((x[to_x] - y) ** 2, -1), dim, distance))
    return LossTerms(coverage + alpha * deviation, coverage, deviation)


def stepwise_l2(x: jax.Array, y: jax.Array, distance: str = "rms",
                mask: jax.Array | None = None) -> LossTerms:
    """The ablation: time-aligned distance, mean over t of d(s_t, g_t) (requires T == M)."""
    if x.shape != y.shape:
        raise ValueError(f"step-wise L2 needs equal lengths, got {x.shape} vs {y.shape}")
    d = _point_distance(jnp.sum((x - y) ** 2, axis=-1), x.shape[-1], distance)
    loss = _masked_mean(d, mask)
    return LossTerms(loss, loss, jnp.zeros_like(loss))


def multi_demo(loss_fn, x: jax.Array, ys: jax.Array, **kw) -> LossTerms:
    """Several demos ys (K, M, D): each rollout is scored against its closest demo (the
    original multi-demo variant keeps the minimum over demos)."""
    terms = jax.vmap(lambda y: loss_fn(x, y, **kw))(ys)
    k = jnp.argmin(terms.loss)
    return LossTerms(*(t[k] for t in terms))


# ---------------------------------------------------------------------------------------
# Per-step gradient normalization (the original code's stabilizer), as a custom_vjp.
# Forward: identity. Backward: non-finite cotangent entries become 0, and if the cotangent's
# global norm exceeds `max_norm` it is rescaled to that norm. Applied to the action and to
# the next state at every step, it keeps one exploding contact from swamping the gradient
# of a whole window.


_OBSERVERS: list = []
"""Callbacks `observe_cotangent_norms` installs: each gets every cotangent norm the
normalizer computes in functions traced while it is installed (diagnostics: the probe)."""


class observe_cotangent_norms:
    """Context manager: functions traced inside it report, through `callback(norm)` (a
    jax.debug.callback, so at run time), the norm of every cotangent the per-step
    normalizer sees (per env, per step: the action's and the next state's), before
    clipping. Functions traced outside it are unchanged."""

    def __init__(self, callback):
        self.callback = callback

    def __enter__(self):
        _OBSERVERS.append(self.callback)
        return self

    def __exit__(self, *exc):
        _OBSERVERS.remove(self.callback)


@jax.custom_vjp
def _norm_leaves(leaves):
    return leaves


def _norm_fwd(leaves):
    return leaves, None


def _norm_bwd(_, cts):
    cts = [jnp.nan_to_num(c, nan=0.0, posinf=0.0, neginf=0.0) for c in cts]
    norm = jnp.sqrt(sum(jnp.sum(c.astype(jnp.float32) ** 2) for c in cts))
    for observe in _OBSERVERS:
        jax.debug.callback(observe, norm)
    scale = jnp.where(norm > 1.0, 1.0 / jnp.maximum(norm, 1e-12), 1.0)
    return ([(c * scale).astype(c.dtype) for c in cts],)


_norm_leaves.defvjp(_norm_fwd, _norm_bwd)


def normalize_grad(tree):
    """Identity on `tree`; in reverse mode, cotangents are cleaned and clipped to norm 1.
    Only floating-point leaves take part (integer leaves have no cotangent)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    idx = [i for i, l in enumerate(leaves) if jnp.issubdtype(jnp.result_type(l), jnp.inexact)]
    if not idx:
        return tree
    normed = _norm_leaves([leaves[i] for i in idx])
    for i, v in zip(idx, normed):
        leaves[i] = v
    return jax.tree_util.tree_unflatten(treedef, leaves)
