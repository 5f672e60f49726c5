"""Small matrix products as elementwise multiply-and-sum: the same function, faster on CPU.

brax's physics multiplies many tiny matrices (3x3 rotations and inertias, a generalized
system's mass matrix and its Newton-Schulz inverse, constraint Jacobians), and vmapping a
step over B environments turns each into a batched `dot_general` of B tiny products. XLA's
CPU runtime runs every dot as a library call (one Eigen product per batch element; no XLA
flag of jaxlib 0.7.2 changes this), so a batch of tiny products costs several times what
the same arithmetic as a broadcast multiply and a sum costs, which also fuses with its
neighbours. Reverse mode doubles the count: each dot's transpose
is two more dots, where a multiply-and-sum's is a broadcast multiply.

`small_dots_as_sums(f)` traces `f` to a jaxpr and evaluates it with every `dot_general`
whose broadcast product is small rewritten as `sum(lhs * rhs)` over the contracting axes,
recursing into the bodies of `scan`, `while`, `cond`, `jax.checkpoint` and nested `jit` calls;
custom-derivative calls (brax's `safe_norm`) are bound unchanged, so their rules stay theirs.
The result is the same function to float round-off (a sum's order may differ from Eigen's),
with the same gradient: it is traced like any other JAX function, under jit, vmap and grad.
Large products (a policy network's layers) are left as dots.
"""
from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from jax import lax
from jax.extend import core

MAX_TERMS = 4096
"""A dot is rewritten when its broadcast product (output size x contracted size, per call
of the traced function, before any vmap) has at most this many terms."""


def _dot_as_sum(lhs, rhs, dimension_numbers, preferred_element_type=None, **_):
    """dot_general(lhs, rhs) as a broadcast multiply and a sum: output axes in dot_general's
    order (batch, lhs free, rhs free)."""
    (lc, rc), (lb, rb) = dimension_numbers
    lf = [i for i in range(lhs.ndim) if i not in lc and i not in lb]
    rf = [i for i in range(rhs.ndim) if i not in rc and i not in rb]
    dtype = preferred_element_type or jnp.result_type(lhs, rhs)
    lhs = lax.transpose(lhs, (*lb, *lf, *lc)).astype(dtype)
    rhs = lax.transpose(rhs, (*rb, *rf, *rc)).astype(dtype)
    nb, nc = len(lb), len(lc)
    # (batch, lhs free, 1 x rhs free, contracting) x (batch, 1 x lhs free, rhs free, contracting)
    lhs = lhs.reshape(lhs.shape[:nb + len(lf)] + (1,) * len(rf) + lhs.shape[nb + len(lf):])
    rhs = rhs.reshape(rhs.shape[:nb] + (1,) * len(lf) + rhs.shape[nb:])
    prod = lhs * rhs
    return jnp.sum(prod, axis=tuple(range(prod.ndim - nc, prod.ndim))) if nc else prod


def _small(eqn, max_terms: int) -> bool:
    (lc, _), _ = eqn.params["dimension_numbers"]
    out = eqn.outvars[0].aval
    lhs = eqn.invars[0].aval
    if not jnp.issubdtype(out.dtype, jnp.floating):
        return False
    terms = math.prod(out.shape) * math.prod(lhs.shape[i] for i in lc)
    return terms <= max_terms


def _fun(closed: core.ClosedJaxpr, max_terms: int):
    """A closed jaxpr as a function of its inputs (a list), evaluated with the rewrite."""
    return lambda *args: _eval(closed.jaxpr, closed.consts, args, max_terms)


def _eval(jaxpr: core.Jaxpr, consts, args, max_terms: int) -> list:
    env = {}

    def read(v):
        return v.val if isinstance(v, core.Literal) else env[v]

    for v, x in zip(jaxpr.constvars, consts):
        env[v] = x
    for v, x in zip(jaxpr.invars, args):
        env[v] = x
    for eqn in jaxpr.eqns:
        invals = [read(v) for v in eqn.invars]
        outs = _eval_eqn(eqn, invals, max_terms)
        if not eqn.primitive.multiple_results:
            outs = [outs]
        for v, x in zip(eqn.outvars, outs):
            env[v] = x
    return [read(v) for v in jaxpr.outvars]


def _rewritten(param, max_terms: int):
    """A primitive's parameter with every closed jaxpr in it (scan's and while's bodies,
    cond's branches) replaced by its rewrite, traced on the same input types; other
    parameters as they are. The primitive is then bound with its own parameters, whatever
    JAX names them (jax 0.11.2's scan has no `num_consts` parameter, which re-calling
    lax.scan on the split operands needed; checked on the GPU image)."""
    if isinstance(param, tuple) and param and all(isinstance(b, core.ClosedJaxpr)
                                                  for b in param):
        return tuple(_rewritten(b, max_terms) for b in param)
    if not isinstance(param, core.ClosedJaxpr):
        return param
    args = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type)
            for a in param.in_avals]
    return jax.make_jaxpr(_fun(param, max_terms))(*args)


def _eval_eqn(eqn, invals, max_terms: int):
    name, p = eqn.primitive.name, eqn.params
    if name == "dot_general" and _small(eqn, max_terms):
        return _dot_as_sum(*invals, **p)
    if name in ("jit", "pjit", "closed_call", "core_call"):
        return _fun(p["jaxpr"] if isinstance(p["jaxpr"], core.ClosedJaxpr)
                    else core.ClosedJaxpr(p["jaxpr"], ()), max_terms)(*invals)
    if name in ("scan", "while", "cond"):  # bodies rewritten in place, bound as they were
        return eqn.primitive.bind(*invals, **{k: _rewritten(v, max_terms)
                                              for k, v in p.items()})
    if name in ("checkpoint", "remat2"):  # jax.checkpoint (jax 0.7 names it remat2)
        inner = core.ClosedJaxpr(p["jaxpr"], ())
        return jax.checkpoint(_fun(inner, max_terms), prevent_cse=p["prevent_cse"],
                              policy=p["policy"])(*invals)
    subfuns, params = _bind_params(eqn.primitive, p)
    return eqn.primitive.bind(*subfuns, *invals, **params)


def _bind_params(primitive, params) -> tuple:
    """(subfuns, params) to bind `primitive` with: jax 0.7's `get_bind_params` returns that
    pair, jax 0.11's the parameters alone (the rewrite failed on jax 0.11.2 until it took
    both)."""
    bind = primitive.get_bind_params(params)
    return ((), bind) if isinstance(bind, dict) else tuple(bind)


def small_dots_as_sums(f, max_terms: int = MAX_TERMS):
    """`f` with its small matrix products computed as multiply-and-sum (module docstring):
    the same values to float round-off, and the same gradient."""
    @functools.wraps(f)
    def wrapped(*args):
        closed, shape = jax.make_jaxpr(f, return_shape=True)(*args)
        out = _eval(closed.jaxpr, closed.consts, jax.tree_util.tree_leaves(args), max_terms)
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(shape), out)
    return wrapped
