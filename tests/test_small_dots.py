"""tasks.physics.small_dots: small matrix products as multiply-and-sum, the same function and
gradient."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from tasks import make_task
from tasks.physics.small_dots import _dot_as_sum, small_dots_as_sums


def count_dots(jaxpr) -> int:
    """dot_general equations in a jaxpr and every jaxpr nested in its equations' params."""
    n = 0
    for eqn in jaxpr.eqns:
        n += eqn.primitive.name == "dot_general"
        for v in eqn.params.values():
            for q in v if isinstance(v, (tuple, list)) else [v]:
                if isinstance(q, jax.extend.core.ClosedJaxpr):
                    n += count_dots(q.jaxpr)
                elif isinstance(q, jax.extend.core.Jaxpr):
                    n += count_dots(q)
    return n


@pytest.mark.parametrize("lhs_shape,rhs_shape,dims", [
    ((3, 4), (4, 5), (((1,), (0,)), ((), ()))),            # matrix @ matrix
    ((4,), (4,), (((0,), (0,)), ((), ()))),                # vector . vector
    ((2, 3, 4), (2, 4, 5), (((2,), (1,)), ((0,), (0,)))),  # batched matmul
    ((4, 3), (5, 4), (((0,), (1,)), ((), ()))),            # contracting axes not last/first
    ((3,), (5,), (((), ()), ((), ()))),                    # outer product, nothing contracted
    ((2, 3, 4, 2), (4, 2, 2, 6), (((2, 3), (0, 2)), ((0,), (1,)))),  # two of each, permuted
])
def test_dot_as_sum_equals_dot_general(lhs_shape, rhs_shape, dims):
    """The rewrite of one dot_general: the same axes in dot_general's output order (batch,
    lhs free, rhs free) and the same values as float64 numpy's product."""
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    lhs = jax.random.normal(k1, lhs_shape)
    rhs = jax.random.normal(k2, rhs_shape)
    want = lax.dot_general(lhs, rhs, dims, precision=lax.Precision.HIGHEST)
    got = _dot_as_sum(lhs, rhs, dims)
    assert got.shape == want.shape and got.dtype == want.dtype
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    if dims == (((1,), (0,)), ((), ())):  # and by hand in float64
        np.testing.assert_allclose(got, np.asarray(lhs, np.float64) @ np.asarray(rhs, np.float64),
                                   rtol=1e-5, atol=1e-5)


def test_dot_as_sum_keeps_the_preferred_element_type():
    a = jnp.arange(6, dtype=jnp.float32).reshape(2, 3)
    out = _dot_as_sum(a, a, (((1,), (1,)), ((), ())), preferred_element_type=jnp.float64
                      if jax.config.jax_enable_x64 else jnp.float32)
    np.testing.assert_array_equal(out, np.array([[5.0, 14.0], [14.0, 50.0]]))


def _nested(a, b, w):
    """Small products inside jit, scan, while, cond, checkpoint and a custom_jvp function,
    and one large product (w: 64 x 128) that must stay a dot."""
    @jax.custom_jvp
    def safe(x):
        return jnp.sqrt(jnp.sum(x * x) + 1.0)

    @safe.defjvp
    def _(p, t):
        (x,), (dx,) = p, t
        return safe(x), jnp.sum(x * dx) / safe(x)

    @jax.jit
    def mix(x):
        return jnp.tanh(a @ x)

    def body(x, _):
        return jax.checkpoint(mix)(x) @ b, None

    x, _ = lax.scan(body, b, None, length=3)
    # a while loop has no reverse mode (brax's run forward only): its input carries no gradient
    a0 = lax.stop_gradient(a)
    xw = lax.while_loop(lambda c: c[1] < 2, lambda c: (jnp.tanh(a0 @ c[0]), c[1] + 1),
                        (lax.stop_gradient(x), 0))[0]
    x = x + xw
    x = lax.cond(jnp.sum(x) > 0, lambda y: a @ y, lambda y: y @ a, x)
    big = jnp.tanh(jnp.ones((1, 64)) @ w)
    return jnp.sum(x) * safe(x) + jnp.sum(big)


def test_rewrite_keeps_value_and_gradient_through_control_flow():
    """Through scan, while, cond, checkpoint and nested jit: the same value and gradient;
    every small dot is gone from the traced function and the large one is kept."""
    k = jax.random.split(jax.random.PRNGKey(1), 3)
    a = 0.5 * jax.random.normal(k[0], (4, 4))
    b = 0.5 * jax.random.normal(k[1], (4, 4))
    w = 0.1 * jax.random.normal(k[2], (64, 128))
    fast = small_dots_as_sums(_nested)
    v0, g0 = jax.value_and_grad(_nested, argnums=(0, 1, 2))(a, b, w)
    v1, g1 = jax.jit(jax.value_and_grad(fast, argnums=(0, 1, 2)))(a, b, w)
    assert float(v1) == pytest.approx(float(v0), rel=1e-5)
    for x, y in zip(g1, g0):
        np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5)
    assert count_dots(jax.make_jaxpr(_nested)(a, b, w).jaxpr) == 6  # mix x2, @b, cond x2, big
    assert count_dots(jax.make_jaxpr(fast)(a, b, w).jaxpr) == 1     # only the large one
    # and vmapped (how a physics step runs): the same per-example values
    vb = jax.vmap(fast, in_axes=(0, None, None))(jnp.stack([a, -a]), b, w)
    np.testing.assert_allclose(vb, [v0, _nested(-a, b, w)], rtol=1e-5)


def _three_steps(task, s0, acts):
    from tasks.core import open_loop

    def total(a):
        _, m = open_loop(jax.vmap(task.env.step), s0, a, jax.vmap(task.matched_state))
        return jnp.sum(jnp.sin(m))
    return jax.jit(jax.value_and_grad(total))(acts)


def _same_physics(name: str):
    """with_small_dots on task `name`: the same states and gradient through 3 steps of 2 envs
    as brax's own step, to float32 round-off, and no dot left in the rewritten step; the
    registry's cached task keeps brax's step. Returns (task, one env's pipeline state, one
    action) for further checks."""
    from tasks.physics.transforms import with_small_dots
    task = make_task(name)
    fast = with_small_dots(task)
    assert "pipeline_step" not in vars(task.env.unwrapped)  # the cached env is untouched
    s0 = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), 2))
    acts = 0.8 * jax.random.normal(jax.random.PRNGKey(1), (3, 2, task.action_size))
    (v0, g0), (v1, g1) = _three_steps(task, s0, acts), _three_steps(fast, s0, acts)
    assert float(v1) == pytest.approx(float(v0), rel=1e-5)
    np.testing.assert_allclose(g1, g0, rtol=1e-3, atol=1e-5)
    assert float(jnp.abs(g0).sum()) > 0
    one = jax.tree.map(lambda x: x[0], s0.pipeline_state)
    a = acts[0, 0]
    assert count_dots(jax.make_jaxpr(task.env.unwrapped.pipeline_step)(one, a).jaxpr) > 0
    assert count_dots(jax.make_jaxpr(fast.env.unwrapped.pipeline_step)(one, a).jaxpr) == 0
    return task, one, a


@pytest.mark.slow  # acrobot's step gradient compiled twice; the default run checks the
# rewrite's value and gradient through control flow above
def test_small_dots_is_the_same_physics_and_gradient():
    """acrobot (brax's generalized pipeline, 4 substeps per step): the rewrite above; it
    composes with substep remat as a physics plan applies them (the checkpointed substeps are
    rewritten inside), substep remat refuses to drop it (the other order), and it refuses a
    task with no brax physics step."""
    from tasks.physics import Plan, apply
    from tasks.physics.transforms import with_small_dots, with_substep_remat
    task, one, a = _same_physics("acrobot")
    remat = jax.make_jaxpr(jax.checkpoint(jnp.sin))(1.0).eqns[0].primitive.name + "["
    plan = Plan(small_dots=True, substep_remat=True)
    for both in (apply(task, plan), with_small_dots(with_substep_remat(task))):
        jaxpr = jax.make_jaxpr(both.env.unwrapped.pipeline_step)(one, a)
        assert remat in str(jaxpr) and count_dots(jaxpr.jaxpr) == 0
    with pytest.raises(ValueError, match="acrobot.*apply with_substep_remat first"):
        with_substep_remat(with_small_dots(task))
    with pytest.raises(ValueError, match="pointmass.*small_dots"):
        with_small_dots(make_task("pointmass"))


@pytest.mark.slow
def test_small_dots_swimmer_is_the_same_physics_and_gradient():
    """swimmer (slow: each 3-step gradient compiles in ~55 s on one core): a generalized step
    of 5x5 products (mass matrix and its Newton-Schulz inverse) and a joint-limit solve
    (jaxopt's loops: scan, while and cond bodies rewritten); and on the joint-limit-free copy
    with substep remat."""
    from tasks.core import without_joint_limits
    from tasks.physics.transforms import with_small_dots, with_substep_remat
    task, _, _ = _same_physics("swimmer")
    free = without_joint_limits(task)
    both = with_small_dots(with_substep_remat(free))
    assert both.env.unwrapped.sys.dof.limit is None
    s0 = jax.vmap(free.env.reset)(jax.random.split(jax.random.PRNGKey(0), 2))
    acts = 0.8 * jax.random.normal(jax.random.PRNGKey(1), (3, 2, task.action_size))
    (v2, g2), (v3, g3) = _three_steps(free, s0, acts), _three_steps(both, s0, acts)
    assert float(v3) == pytest.approx(float(v2), rel=1e-5)
    np.testing.assert_allclose(g3, g2, rtol=1e-3, atol=1e-5)


def test_rewrite_binds_primitives_under_either_get_bind_params_contract():
    """jax 0.7's `Primitive.get_bind_params` returns (subfuns, params), jax 0.11's the params
    alone (the rewrite failed on the GPU image's jax 0.11.2 until it took both): either way
    the rewrite binds with the subfuns and the parameters the primitive gave back, and
    jax 0.7's own primitives still answer with the pair."""
    from tasks.physics.small_dots import _bind_params

    class Old:
        def get_bind_params(self, params):
            return ["f"], {**params, "extra": 1}

    class New:
        def get_bind_params(self, params):
            return {k: v for k, v in params.items() if k != "drop"}

    assert _bind_params(Old(), {"a": 2}) == (["f"], {"a": 2, "extra": 1})
    assert _bind_params(New(), {"a": 2, "drop": 3}) == ((), {"a": 2})
    subfuns, params = _bind_params(lax.sin_p, {"accuracy": None})
    assert list(subfuns) == [] and params == {"accuracy": None}
