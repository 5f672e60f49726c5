"""ILD: hand-computed losses, gradient stability at the extremes, equivalences, learning."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from bench.budget import Budget
from bench.evaluator import EvalConfig
from bench.runner import RunRequest, execute, prepare
from methods.common.policy import ObsNorm, TanhGaussianPolicy
from methods.ild.config import ILDConfig
from methods.ild.losses import (chamfer_alpha, multi_demo, nearest, normalize_grad,
                                pairwise_distance, stepwise_l2)
from methods.ild.train import StateNorm, make_rollout_loss
from tasks import make_task
from tasks.demo import load_demo

X = jnp.array([[0.0], [3.0]])
Y = jnp.array([[0.0], [1.0]])


def test_chamfer_by_hand_squared():
    # deviation: x=0 -> 0, x=3 -> min(9, 4) = 4: mean 2. coverage: y=0 -> 0, y=1 -> 1: 0.5
    t = chamfer_alpha(X, Y, alpha=1.0, distance="sq")
    assert (float(t.deviation), float(t.coverage)) == (2.0, 0.5)
    assert float(chamfer_alpha(X, Y, alpha=5.0, distance="sq").loss) == 0.5 + 5 * 2.0
    assert float(chamfer_alpha(X, Y, alpha=0.0, distance="sq").loss) == 0.5


def test_chamfer_by_hand_rms():
    # D = 2: d = sqrt(mean_D (x - y)^2). x=(3,4) to y=(0,0): sqrt(25/2)
    x = jnp.array([[3.0, 4.0], [0.0, 0.0]])
    y = jnp.array([[0.0, 0.0]])
    t = chamfer_alpha(x, y, alpha=1.0, distance="rms")
    np.testing.assert_allclose(t.deviation, np.sqrt(12.5) / 2, rtol=1e-6)
    np.testing.assert_allclose(t.coverage, 0.0, atol=1e-7)


def test_nearest_matches_brute_force():
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    x, y = jax.random.normal(k1, (128, 40)), jax.random.normal(k2, (128, 40))
    d = pairwise_distance(x, y, "sq")
    to_y, to_x = nearest(x, y)
    np.testing.assert_array_equal(to_y, jnp.argmin(d, 1))
    np.testing.assert_array_equal(to_x, jnp.argmin(d, 0))
    t = chamfer_alpha(x, y, 0.7, "rms")
    brute = pairwise_distance(x, y, "rms")
    np.testing.assert_allclose(t.loss, brute.min(0).mean() + 0.7 * brute.min(1).mean(),
                               rtol=1e-6)


@pytest.mark.parametrize("distance", ["rms", "sq", "msq"])
def test_gradient_is_finite_when_rollout_equals_demo(distance):
    y = jax.random.normal(jax.random.PRNGKey(1), (16, 5))
    g = jax.grad(lambda x: chamfer_alpha(x, y, 1.0, distance).loss)(y)
    assert np.isfinite(np.asarray(g)).all()
    np.testing.assert_array_equal(g, 0.0)  # the minimum: zero gradient, not NaN


def test_stepwise_l2_and_multi_demo():
    t = stepwise_l2(X, Y, distance="sq")  # (0 + 4) / 2
    assert float(t.loss) == 2.0
    x2, y2 = jnp.array([[0.0, 0.0], [3.0, 1.0]]), jnp.array([[0.0, 0.0], [1.0, 1.0]])
    assert float(stepwise_l2(x2, y2, distance="sq").loss) == 2.0   # (0 + 4) / 2
    assert float(stepwise_l2(x2, y2, distance="msq").loss) == 1.0  # (0 + 4 / 2) / 2
    ys = jnp.stack([Y, X])  # the second demo equals the rollout
    assert float(multi_demo(chamfer_alpha, X, ys, alpha=1.0, distance="sq").loss) == 0.0
    with pytest.raises(ValueError, match="equal lengths"):
        stepwise_l2(X, Y[:1])


def test_normalize_grad_forward_identity_backward_clipped():
    x = jnp.array([3.0, 4.0])
    np.testing.assert_array_equal(normalize_grad(x), x)
    g = jax.grad(lambda x: jnp.sum(normalize_grad(x) * jnp.array([30.0, 40.0])))(x)
    np.testing.assert_allclose(g, [0.6, 0.8], rtol=1e-6)  # norm 50 -> 1
    g = jax.grad(lambda x: jnp.sum(normalize_grad(x) * jnp.array([0.3, 0.4])))(x)
    np.testing.assert_allclose(g, [0.3, 0.4], rtol=1e-6)  # norm 0.5 < 1: unchanged
    g = jax.grad(lambda x: jnp.sum(normalize_grad(x) * jnp.array([jnp.nan, 0.5])))(x)
    np.testing.assert_allclose(g, [0.0, 0.5])  # NaN cotangent -> 0
    tree = {"f": jnp.ones(2), "i": jnp.array([1, 2])}
    assert normalize_grad(tree)["i"].dtype == jnp.int32  # int leaves pass through


def test_observed_cotangent_norms_are_the_normalizers_inputs():
    """observe_cotangent_norms (the probe's count of what the per-step normalizer clips)
    reports each cotangent's norm before clipping, per vmapped example, and only in
    functions traced while it is installed."""
    from methods.ild.losses import observe_cotangent_norms
    x = jnp.array([[3.0, 4.0], [1.0, 1.0]])
    w = jnp.array([[30.0, 40.0], [0.3, 0.4]])  # cotangents of norm 50 and 0.5

    def f(x):
        return jnp.sum(jax.vmap(normalize_grad)(x) * w)

    seen = []
    with observe_cotangent_norms(seen.append):
        g = jax.jit(jax.grad(f))(x)
        jax.effects_barrier()
    np.testing.assert_allclose(sorted(np.ravel(seen)), [0.5, 50.0], rtol=1e-6)
    np.testing.assert_allclose(g, [[0.6, 0.8], [0.3, 0.4]], rtol=1e-6)
    jax.block_until_ready(jax.jit(jax.grad(lambda x: f(x) * 2.0))(x))  # traced outside
    jax.effects_barrier()
    assert len(np.ravel(seen)) == 2


# --- the full rollout loss on pointmass -------------------------------------------------

class _ModePolicy(TanhGaussianPolicy):
    """Acts with the mode: no sampling, so float32 and float64 see the same actions (JAX
    draws different numbers from one key at different precisions)."""

    def sample(self, params, obs, key):
        return self.mode(params, obs)

    def sample_batch(self, params, obs, keys, kernels_t, swish_remat=True, taps=None):
        return self.mode(params, obs)


def _setup(config, dtype=jnp.float32, deterministic=False):
    task = make_task("pointmass")
    demo = load_demo(task.spec.demo_path, task)
    if deterministic:  # no reset noise either
        from tasks.core import Canonical, Task
        from tasks.pointmass import PointMass
        task = Task(spec=task.spec, env=Canonical(PointMass(reset_noise_scale=0.0)))
    ds = jnp.asarray(demo.states[:1, 1:], dtype)
    flat = ds.reshape(-1, ds.shape[-1])
    norm = StateNorm(flat.mean(0), jnp.sqrt(jnp.clip(flat.var(0), 0.01, 1e6)))
    cls = _ModePolicy if deterministic else TanhGaussianPolicy
    policy = cls(task.obs_size, task.action_size, config.hidden)
    params = policy.init(jax.random.PRNGKey(0), ObsNorm.fit(jnp.asarray(demo.obs[0])))
    params = jax.tree.map(lambda x: jnp.asarray(x, dtype), params)
    loss = make_rollout_loss(task, policy, norm(ds), norm, config)
    keys = jax.random.split(jax.random.PRNGKey(1), config.num_envs)
    return loss, params, keys


def _cfg(**kw):
    return dataclasses.replace(ILDConfig(num_envs=4, hidden=(32, 32)), **kw)


@pytest.mark.parametrize("kw", [dict(truncation=1), dict(truncation=128), dict(alpha=0.0),
                                dict(alpha=5.0), dict(loss="l2"), dict(distance="sq"),
                                dict(grad_normalization=False, tanh_loss=False)])
def test_rollout_gradient_finite_at_the_extremes(kw):
    loss, params, keys = _setup(_cfg(**kw))
    (v, aux), g = jax.jit(jax.value_and_grad(loss, has_aux=True))(params, jax.random.PRNGKey(2),
                                                                   keys)
    flat = np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(g)])
    assert np.isfinite(v) and np.isfinite(flat).all() and np.abs(flat).sum() > 0


def test_grad_norm_scope_batch_is_one_norm_over_all_envs():
    """grad_norm_scope: 'env' (default) normalizes each env's per-step cotangents on their
    own, 'batch' (the original's) all B envs' at once. Where no norm reaches 1 (the loss
    scaled by 0.1; unscaled, one of pointmass's batch norms is 1.37 while its envs' stay
    under 0.72) they are the same gradient, and each batch norm squared is the sum of the
    envs' squared norms at that step (one norm per step and kind instead of B); with the
    loss scaled by 1e4 they clip,
    the batch's one norm caps all envs' cotangent together, and its gradient is the smaller."""
    from methods.ild.losses import observe_cotangent_norms
    T, B = make_task("pointmass").episode_length, 4
    out = {}
    for scope in ("env", "batch"):
        loss, params, keys = _setup(_cfg(grad_norm_scope=scope))
        for scale in (0.1, 1e4):
            seen = []
            with observe_cotangent_norms(seen.append):
                g = jax.jit(jax.grad(lambda p: scale * loss(p, jax.random.PRNGKey(2),
                                                            keys)[0]))(params)
                jax.effects_barrier()
            out[scope, scale] = (g, np.concatenate([np.ravel(n) for n in seen]))
    (ge, ne), (gb, nb) = out["env", 0.1], out["batch", 0.1]
    assert (ne.size, nb.size) == (2 * T * B, 2 * T) and 0 < ne.max() <= nb.max() < 1
    np.testing.assert_allclose(np.sum(nb ** 2), np.sum(ne ** 2), rtol=1e-4)
    for a, b in zip(jax.tree.leaves(ge), jax.tree.leaves(gb)):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-9)
    (ge, ne), (gb, nb) = out["env", 1e4], out["batch", 1e4]
    assert (ne > 1).mean() >= 0.25 and (nb > 1).mean() >= 0.25
    assert float(optax.global_norm(gb)) < 0.9 * float(optax.global_norm(ge))
    with pytest.raises(ValueError, match="grad_norm_scope must be one of"):
        _cfg(grad_norm_scope="step")


def test_observation_normalizer_is_frozen_in_ild_and_bc():
    """The policy's normalizer statistics live in params (a saved policy carries them) but
    are fixed: zero gradient from the ILD loss and the BC loss, and unchanged bit for bit by
    a BC warm start (before bc v2 / ild v4 Adam moved them: hopper's std 1.0 -> 0.81)."""
    from methods.common.policy import bc_loss
    from methods.ild.train import bc_warm_start
    loss, params, keys = _setup(_cfg())
    g = jax.grad(lambda p: loss(p, jax.random.PRNGKey(2), keys)[0])(params)
    assert np.abs(np.ravel(g["net"]["params"]["hidden_0"]["kernel"])).sum() > 0
    assert not np.any(g["norm"].mean) and not np.any(g["norm"].std)
    task = make_task("pointmass")
    demo = load_demo(task.spec.demo_path, task)
    obs = jnp.asarray(demo.obs[:, :-1]).reshape(-1, task.obs_size)
    act = jnp.asarray(demo.actions).reshape(-1, task.action_size)
    policy = TanhGaussianPolicy(task.obs_size, task.action_size, (32, 32))
    p0 = policy.init(jax.random.PRNGKey(0), ObsNorm.fit(obs, 1.0))
    gb = jax.grad(lambda p: bc_loss(policy, p, obs, act, jax.random.PRNGKey(3), 4))(p0)
    assert not np.any(gb["norm"].mean) and not np.any(gb["norm"].std)
    p1, _ = bc_warm_start(policy, p0, obs, act, _cfg(bc_updates=50), jax.random.PRNGKey(4))
    np.testing.assert_array_equal(p1["norm"].mean, p0["norm"].mean)
    np.testing.assert_array_equal(p1["norm"].std, p0["norm"].std)
    assert not np.array_equal(p1["net"]["params"]["hidden_0"]["kernel"],
                              p0["net"]["params"]["hidden_0"]["kernel"])


def test_tanh_loss_saturates_to_a_zero_gradient():
    """Why tanh_loss is off by default: far from the demo the original's tanh(L) is exactly
    1 in float32 and the gradient exactly 0; without tanh the same point has a gradient."""
    far = jnp.full((8, 3), 30.0)
    y = jnp.zeros((8, 3))
    g_tanh = jax.grad(lambda x: jnp.tanh(chamfer_alpha(x, y).loss))(far)
    g_raw = jax.grad(lambda x: chamfer_alpha(x, y).loss)(far)
    assert float(jnp.abs(g_tanh).sum()) == 0.0 and float(jnp.abs(g_raw).sum()) > 0


def test_gradient_finite_with_saturated_actions():
    loss, params, keys = _setup(_cfg())
    # Push the last layer's bias so every action is tanh(~+20) = +1 (saturated).
    last = sorted(params["net"]["params"])[-1]
    b = params["net"]["params"][last]["bias"]
    params["net"]["params"][last]["bias"] = b.at[: b.shape[0] // 2].set(20.0)
    (v, aux), g = jax.value_and_grad(loss, has_aux=True)(params, jax.random.PRNGKey(2), keys)
    assert float(aux["train/action_abs"]) > 0.999
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(g))


def test_float32_and_float64_agree():
    cfg = _cfg(grad_normalization=False)
    loss32, p32, keys = _setup(cfg, deterministic=True)
    v32, g32 = jax.value_and_grad(lambda p: loss32(p, jax.random.PRNGKey(2), keys)[0])(p32)
    with jax.experimental.enable_x64():
        loss64, p64, keys64 = _setup(cfg, jnp.float64, deterministic=True)
        v64, g64 = jax.value_and_grad(lambda p: loss64(p, jax.random.PRNGKey(2), keys64)[0])(
            p64)
        assert jax.tree_util.tree_leaves(g64)[0].dtype == jnp.float64
    np.testing.assert_allclose(v32, v64, rtol=1e-4)
    for a, b in zip(jax.tree_util.tree_leaves(g32), jax.tree_util.tree_leaves(g64)):
        np.testing.assert_allclose(a, b, rtol=2e-3, atol=1e-5)


def test_analytic_gradient_matches_finite_differences():
    """float64, through 128 steps of pointmass physics and the Chamfer loss, w.r.t. the
    policy's output bias (one direction, central differences)."""
    with jax.experimental.enable_x64():
        cfg = _cfg(grad_normalization=False, truncation=128, distance="sq", tanh_loss=False)
        loss, params, keys = _setup(cfg, jnp.float64)
        last = sorted(params["net"]["params"])[-1]

        def f(eps):
            p = jax.tree.map(lambda x: x, params)
            b = p["net"]["params"][last]["bias"]
            p["net"]["params"][last]["bias"] = b.at[0].add(eps)
            return loss(p, jax.random.PRNGKey(2), keys)[0]

        analytic = jax.grad(f)(0.0)
        h = 1e-5
        numeric = (f(h) - f(-h)) / (2 * h)
        assert abs(float(analytic)) > 1e-6
        np.testing.assert_allclose(analytic, numeric, rtol=1e-4)


def test_remat_computes_the_same_loss_and_gradient():
    """remat=True (jax.checkpoint on each step, ant's override) recomputes the
    forward inside the backward pass: the same loss and gradient, to float32 round-off,
    with per-step gradient normalization and truncation in the path."""
    out = {}
    for remat in (False, True):
        loss, params, keys = _setup(_cfg(remat=remat, truncation=10))
        out[remat] = jax.jit(jax.value_and_grad(lambda p: loss(p, jax.random.PRNGKey(2),
                                                               keys)[0]))(params)
    assert float(out[False][0]) == pytest.approx(float(out[True][0]), rel=1e-6)
    for a, b in zip(jax.tree_util.tree_leaves(out[False][1]),
                    jax.tree_util.tree_leaves(out[True][1])):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-7)
    assert sum(float(jnp.abs(x).sum()) for x in jax.tree_util.tree_leaves(out[True][1])) > 0


def test_sample_batch_is_vmapped_sample_with_the_same_gradient():
    """TanhGaussianPolicy.sample_batch (transposed_backward) draws the same actions as
    vmap(sample) from the same keys, bit for bit, and its custom backward (dense_t: the
    kernels' transposes made once, the kernel's cotangent one product over every leading
    axis) gives autodiff's gradient in params and obs."""
    from methods.common.policy import dense_t
    policy = TanhGaussianPolicy(5, 2, (16, 8))
    params = policy.init(jax.random.PRNGKey(0), ObsNorm(jnp.full(5, 0.1), jnp.full(5, 2.0)))
    obs = jax.random.normal(jax.random.PRNGKey(1), (6, 5))
    keys = jax.random.split(jax.random.PRNGKey(2), 6)
    w = jax.random.normal(jax.random.PRNGKey(3), (6, 2))
    vmapped = jax.vmap(policy.sample, in_axes=(None, 0, 0))

    def loss(p, o, batch):
        a = (policy.sample_batch(p, o, keys, policy.kernels_t(p)) if batch
             else vmapped(p, o, keys))
        return jnp.sum(jnp.sin(3 * a) * w)

    np.testing.assert_array_equal(policy.sample_batch(params, obs, keys,
                                                      policy.kernels_t(params)),
                                  vmapped(params, obs, keys))
    ref, new = (jax.grad(loss, argnums=(0, 1))(params, obs, b) for b in (False, True))
    for a, b in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(new)):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-7)
    assert float(jnp.abs(new[0]["net"]["params"]["hidden_1"]["kernel"]).sum()) > 0
    # dense_t on a (2, 3, 4) input: kernel's cotangent sums over both leading axes
    x = jax.random.normal(jax.random.PRNGKey(4), (2, 3, 4))
    k = jax.random.normal(jax.random.PRNGKey(5), (4, 7))
    g = jax.random.normal(jax.random.PRNGKey(6), (2, 3, 7))
    new = jax.vjp(lambda x, k: dense_t(x, k, k.T), x, k)[1](g)
    ref = jax.vjp(lambda x, k: x @ k, x, k)[1](g)
    for a, b in zip(ref, new):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6)


def test_transposed_backward_computes_the_same_loss_and_gradient():
    """transposed_backward=True (the default) runs the rollout's policy as one batched sample_batch per
    step: the same loss and gradient (per-step gradient normalization and truncation in the
    path), with the kernels transposed once, outside the scan."""
    out, jaxprs = {}, {}
    for t in (False, True):
        loss, params, keys = _setup(_cfg(transposed_backward=t, truncation=10))
        f = jax.value_and_grad(lambda p: loss(p, jax.random.PRNGKey(2), keys)[0])
        out[t] = jax.jit(f)(params)
        jaxprs[t] = jax.make_jaxpr(f)(params)
    assert float(out[False][0]) == pytest.approx(float(out[True][0]), rel=1e-6)
    for a, b in zip(jax.tree_util.tree_leaves(out[False][1]),
                    jax.tree_util.tree_leaves(out[True][1])):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-7)
    assert sum(float(jnp.abs(x).sum()) for x in jax.tree_util.tree_leaves(out[True][1])) > 0
    # the kernels' transposes, (32, 2), (32, 32) and (2, 32), made once outside the scans
    def transposed(j):
        return [e.outvars[0].aval.shape for e in j.jaxpr.eqns if e.primitive.name == "transpose"]
    assert [(32, 2), (32, 32), (2, 32)] == [s for s in transposed(jaxprs[True]) if 32 in s]
    assert not [s for s in transposed(jaxprs[False]) if 32 in s]


def test_swish_dense_t_is_reverse_mode_of_swish_then_the_product_bit_for_bit():
    """swish_dense_t(h, k, k.T) = swish(h) @ k, its backward keeping only h: the same value
    and the same cotangents in h and k as reverse mode of linen.swish then the product, bit
    for bit, under jit, on pre-activations from 0 to +-1e4 (where sigmoid rounds to 0 and 1)
    and over two leading axes; at +-inf both give the same non-finite cotangents."""
    from flax import linen
    from methods.common.policy import swish_dense_t
    h = jnp.concatenate([jax.random.normal(jax.random.PRNGKey(0), (2, 5, 6)) * 4,
                         jnp.array([0.0, 1e-30, -20.0, 30.0, -1e4, 1e4]).reshape(1, 1, 6)
                         * jnp.ones((2, 1, 6))], axis=1)
    k = jax.random.normal(jax.random.PRNGKey(1), (6, 7))
    g = jax.random.normal(jax.random.PRNGKey(2), (2, 6, 7))

    def vjp(f, h):
        out, back = jax.vjp(f, h, k)
        return (out, *back(g))

    new = jax.jit(lambda h: vjp(lambda h, k: swish_dense_t(h, k, k.T), h))(h)
    ref = jax.jit(lambda h: vjp(lambda h, k: linen.swish(h) @ k, h))(h)
    for a, b in zip(ref, new):
        np.testing.assert_array_equal(b, a)
    assert np.isfinite(np.asarray(new[1])).all() and float(jnp.abs(new[2]).sum()) > 0
    # sigmoid(-1e4) = 0 and sigmoid(1e4) = 1: h's cotangent there is 0 and g @ k.T
    np.testing.assert_array_equal(new[1][:, -1, 4], 0.0)
    np.testing.assert_allclose(new[1][:, -1, 5], (g @ k.T)[:, -1, 5], rtol=1e-6)
    h_inf = h.at[0, 0, 0].set(jnp.inf).at[1, 0, 0].set(-jnp.inf)
    new = jax.jit(lambda h: vjp(lambda h, k: swish_dense_t(h, k, k.T), h))(h_inf)
    ref = jax.jit(lambda h: vjp(lambda h, k: linen.swish(h) @ k, h))(h_inf)
    for a, b in zip(ref, new):
        np.testing.assert_array_equal(b, a)


def test_swish_remat_is_the_same_update_bit_for_bit_with_fewer_residuals():
    """swish_remat=True (the default) changes what the policy's backward keeps, not what it
    computes: pointmass's loss and gradient through the rollout (truncation and per-step
    normalization in the path) equal swish_remat=False's bit for bit, and XLA's working
    memory for the gradient falls (hidden 512-256, the paper's, B = 4: the policy's stacked
    residuals are most of it)."""
    from benchmarks.ild_speed import temp_bytes
    out, mem = {}, {}
    for remat in (False, True):
        loss, params, keys = _setup(_cfg(swish_remat=remat, truncation=10))
        f = jax.jit(jax.value_and_grad(lambda p: loss(p, jax.random.PRNGKey(2), keys)[0]))
        out[remat] = f(params)
        loss, params, keys = _setup(_cfg(swish_remat=remat, hidden=(512, 256)))
        g = jax.jit(jax.grad(lambda p: loss(p, jax.random.PRNGKey(2), keys)[0]))
        mem[remat] = temp_bytes(g.lower(params).compile())
    assert float(out[True][0]) == float(out[False][0])
    for a, b in zip(jax.tree_util.tree_leaves(out[False][1]),
                    jax.tree_util.tree_leaves(out[True][1])):
        np.testing.assert_array_equal(b, a)
    assert sum(float(jnp.abs(x).sum()) for x in jax.tree_util.tree_leaves(out[True][1])) > 0
    assert mem[True] < 0.7 * mem[False], mem


def test_dense_taps_hand_out_the_kernel_cotangents_factors():
    """dense_tap and swish_dense_tap compute dense_t's and swish_dense_t's value and input
    cotangent bit for bit, make no kernel cotangent, and hand its two factors out as the
    tap's cotangent: (the layer's input, g), whose contract_leading is the kernel cotangent
    dense_t and swish_dense_t make, bit for bit (all under jit)."""
    from methods.common.policy import (contract_leading, dense_t, dense_tap, swish_dense_t,
                                       swish_dense_tap)
    x = jax.random.normal(jax.random.PRNGKey(0), (3, 4, 6)) * 3
    k = jax.random.normal(jax.random.PRNGKey(1), (6, 5))
    g = jax.random.normal(jax.random.PRNGKey(2), (3, 4, 5))
    tap = (jnp.zeros((3, 4, 6)), jnp.zeros((3, 4, 5)))
    for ref_fn, tap_fn, factor in ((dense_t, dense_tap, x),
                                   (swish_dense_t, swish_dense_tap, x * jax.nn.sigmoid(x))):
        out, back = jax.vjp(lambda x_, k_: ref_fn(x_, k_, k.T), x, k)
        ct_x, ct_k = jax.jit(back)(g)
        out_t, back_t = jax.vjp(lambda x_, k_, t_: tap_fn(x_, k_, k.T, t_), x, k, tap)
        ct_x_t, ct_k_t, ct_tap = jax.jit(back_t)(g)
        np.testing.assert_array_equal(out_t, out)
        np.testing.assert_array_equal(ct_x_t, ct_x)
        np.testing.assert_array_equal(ct_k_t, 0.0)
        np.testing.assert_allclose(ct_tap[0], factor, rtol=1e-6)  # XLA fuses sigmoid
        np.testing.assert_array_equal(ct_tap[1], g)
        np.testing.assert_array_equal(contract_leading(*ct_tap), ct_k)
        assert float(jnp.abs(ct_k).sum()) > 0


@pytest.mark.parametrize("kw", [dict(kernel_grad_group=4), dict(kernel_grad_group=16),
                                dict(kernel_grad_group=8, remat=True),
                                dict(kernel_grad_group=4, swish_remat=False)])
def test_kernel_grad_group_is_the_same_rollout_gradient_to_round_off(kw):
    """kernel_grad_group=G runs the rollout in groups of G steps whose backward makes each
    kernel's cotangent once per group: pointmass's loss (truncation 10, per-step
    normalization) equals G = 1's bit for bit, and every gradient leaf G = 1's to float32
    round-off (the kernels' sums over steps in another order)."""
    out = {}
    for extra in ({}, kw):
        base = {k: v for k, v in kw.items() if k != "kernel_grad_group"}
        loss, params, keys = _setup(_cfg(truncation=10, **{**base, **extra}))
        out[bool(extra)] = jax.jit(jax.value_and_grad(
            lambda p: loss(p, jax.random.PRNGKey(2), keys)[0]))(params)
    assert float(out[True][0]) == float(out[False][0])
    flat = jax.tree_util.tree_flatten_with_path(out[False][1])[0]
    for (path, a), b in zip(flat, jax.tree_util.tree_leaves(out[True][1])):
        np.testing.assert_allclose(b, a, rtol=2e-5, atol=1e-6 * float(jnp.abs(a).max()),
                                   err_msg=jax.tree_util.keystr(path))
    kernels = [v for p, v in flat if "kernel" in jax.tree_util.keystr(p)]
    assert len(kernels) == 3 and all(float(jnp.abs(v).sum()) > 0 for v in kernels)


def test_kernel_grad_group_refuses_what_it_cannot_group():
    """A group that does not divide the episode, and grouping without sample_batch's
    transposed backward (no taps to group), are refused by name with the fix."""
    with pytest.raises(ValueError, match="does not divide pointmass's episode"):
        _setup(_cfg(kernel_grad_group=3))
    with pytest.raises(ValueError, match="transposed_backward True or kernel_grad_group 1"):
        ILDConfig(kernel_grad_group=4, transposed_backward=False)
    with pytest.raises(ValueError, match="kernel_grad_group must be >= 1"):
        ILDConfig(kernel_grad_group=0)


def test_chunk_runs_the_same_updates_as_one_per_call():
    """chunk=K (K updates in one jitted call, as the trainer and the speed benchmark's
    ild_chunkK rows run them, and as brax's APG scans an epoch) is a call structure, not a
    different method: 3 updates
    scanned in one call give the parameters 3 separate calls give, to float32 round-off;
    so does the trainer's chunk of 4 told that only 3 are left in the budget (and its
    metrics are their mean)."""
    from methods.ild.train import initial_state, make_chunk, make_update
    task = make_task("pointmass")
    demo = load_demo(task.spec.demo_path, task)
    ds = jnp.asarray(demo.states[:1, 1:])
    norm = StateNorm(jnp.zeros(ds.shape[-1]), jnp.ones(ds.shape[-1]))
    cfg = _cfg()
    policy = TanhGaussianPolicy(task.obs_size, task.action_size, cfg.hidden)
    params = policy.init(jax.random.PRNGKey(0), ObsNorm.fit(jnp.asarray(demo.obs[0])))
    update, opt, _ = make_update(task, policy, norm(ds), norm, cfg, jax.random.PRNGKey(3))
    s0 = initial_state(params, opt, jax.random.PRNGKey(4), cfg)
    one = jax.jit(lambda s: update(s, None)[0])
    looped = one(one(one(s0)))
    scanned, m = jax.jit(lambda s: jax.lax.scan(update, s, None, length=3))(s0)
    assert int(scanned.step) == int(looped.step) == 3
    assert m["train/loss"].shape == (3,)
    moved = 0.0
    for a, b, c in zip(*(jax.tree_util.tree_leaves(x.params) for x in (looped, scanned, s0))):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
        moved += float(jnp.abs(a - c).sum())
    assert moved > 1e-3  # the updates did move the parameters
    part, m4 = make_chunk(update, 4)(s0, jnp.int32(3))
    assert int(part.step) == 3
    np.testing.assert_allclose(m4["train/loss"], np.mean(m["train/loss"]), rtol=1e-5)
    for a, b in zip(*(jax.tree_util.tree_leaves(x) for x in (looped, part))):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_updates_this_call_meets_the_budget_inside_a_chunk():
    """Hand-computed: chunk 4, 4096 env steps per update."""
    from methods.ild.train import updates_this_call
    cfg = _cfg(chunk=4, updates=10)
    n = lambda done=0, s=None, steps=None, u=None: updates_this_call(cfg, done, 4096, s, steps, u)
    assert n() == 4                          # no limit but the chunk
    assert n(done=8) == 2                    # 10 updates in all
    assert n(steps=3 * 4096) == 3            # env-step budget: exact
    assert n(steps=2 * 4096 + 1) == 3        # a partial update left still runs (as chunk 1)
    assert n(s=10.0) == 1                    # no time per update measured yet: one update
    assert n(s=2.5, u=1.0) == 3              # 2.5 s left at 1 s per update: overrun < 1 update
    assert n(s=-1.0, u=1.0) == 1             # never 0: the caller checked should_stop first


def test_chunked_ild_stops_at_an_env_step_budget_inside_a_chunk(store):
    """15 updates' env steps with chunk 4: calls of 4, 4, 4, 3 updates; the record has
    exactly the budget's steps and updates, as chunk 1 would."""
    rec, _ = execute(prepare(_ild(0, bc_updates=0, chunk=4)), store, log=lambda s: None)
    assert rec["status"] == "ok" and rec["env_steps"] == 32 * 128 * 15
    assert rec["train_metrics"]["train/updates"] == 15


def _ild(seed, **over):
    req = RunRequest(method="ild", task="pointmass", seed=seed,
                     budget=Budget(env_steps=32 * 128 * 15, evals=3), preset="cpu",
                     overrides=over, eval=EvalConfig(num_episodes=16))
    return req


def test_ild_learns_pointmass_from_scratch_and_is_deterministic(store, tmp_path):
    from bench.store import Store
    rec, _ = execute(prepare(_ild(0, bc_updates=0)), store, log=lambda s: None)
    assert rec["status"] == "ok" and rec["final_normalized"] >= 0.95
    assert rec["env_steps"] == 32 * 128 * 15
    m = rec["train_metrics"]
    assert m["grad/nonfinite"] == 0 and m["grad/norm_raw"] > 0 and m["train/updates"] == 15
    again, _ = execute(prepare(_ild(0, bc_updates=0)), Store(str(tmp_path / "b")),
                       log=lambda s: None)
    assert again["final_return"] == rec["final_return"]


def test_ild_with_bc_warm_start(store):
    rec, _ = execute(prepare(_ild(1, bc_updates=200)), store, log=lambda s: None)
    assert rec["status"] == "ok" and rec["final_normalized"] >= 0.95
    assert rec["curve"][0]["env_steps"] == 0  # the BC warm start is evaluated first


def test_masked_states_neither_deviate_nor_cover():
    x = jnp.array([[0.0], [1.0], [50.0]])  # the last state is after termination
    y = jnp.array([[0.0], [1.0], [2.0]])
    mask = jnp.array([True, True, False])
    t = chamfer_alpha(x, y, 1.0, "sq", mask=mask)
    # deviation over alive states: (0 + 0) / 2; coverage: y=2 -> nearest alive x=1: 1 / 3
    assert float(t.deviation) == 0.0
    np.testing.assert_allclose(t.coverage, 1.0 / 3.0, rtol=1e-6)
    g = jax.grad(lambda x: chamfer_alpha(x, y, 1.0, "sq", mask=mask).loss)(x)
    assert float(g[2, 0]) == 0.0 and np.isfinite(np.asarray(g)).all()
    assert float(stepwise_l2(x, y, "sq", mask=mask).loss) == 0.0  # alive: (0 + 0) / 2
    assert float(stepwise_l2(x, y, "sq").loss) == 48.0 ** 2 / 3  # unmasked


@pytest.mark.slow  # benchmark tool: every row of it compiled
def test_speed_benchmark_reports_every_part_and_its_ratios():
    """The benchmark's rows on pointmass (no APG: brax's trainer wants a brax env): the
    per-step decomposition rows exist and the ratios are the rows' own quotients."""
    from benchmarks.ild_speed import run
    rows = run("pointmass", batch=4, repeats=1, with_apg=False, chunk=3)
    by = {r["what"]: r for r in rows}
    assert {"forward", "ild", "ild_no_gn", "ild_remat", "ild_chunk3", "ild_remat_chunk3",
            "ild_untransposed", "chamfer", "step_forward", "step_vjp", "policy_forward",
            "policy_vjp"} <= set(by)
    assert not {"ild_hand", "ild_xla"} & set(by)  # brax's spring substep's rows: left out
    r = rows[0]
    # chunk rows: 3 updates per call, seconds and env-steps/s per update
    assert by["ild_chunk3"]["updates_per_call"] == 3 and by["ild"]["updates_per_call"] == 1
    assert by["ild_chunk3"]["env_steps_per_s"] == pytest.approx(
        4 * 128 / by["ild_chunk3"]["seconds"], rel=0.02)
    assert r["chunk_speedup"] == pytest.approx(
        by["ild"]["seconds"] / by["ild_chunk3"]["seconds"], rel=0.02, abs=2e-3)
    assert r["transposed_speedup"] == pytest.approx(
        by["ild_untransposed"]["seconds"] / by["ild"]["seconds"], rel=0.02, abs=2e-3)
    assert r["update_over_forward"] == pytest.approx(
        by["ild"]["seconds"] / by["forward"]["seconds"], rel=0.02, abs=2e-3)
    assert r["step_vjp_over_forward"] == pytest.approx(
        by["step_vjp"]["seconds"] / by["step_forward"]["seconds"], rel=0.02, abs=2e-3)
    assert by["step_vjp"]["env_steps_per_s"] == pytest.approx(4 / by["step_vjp"]["seconds"],
                                                              rel=0.02)
    assert by["forward"]["env_steps_per_s"] == pytest.approx(4 * 128 / by["forward"]["seconds"],
                                                             rel=0.02)
    # working memory: the update keeps the backward pass's residuals, which a forward
    # rollout does not and rematerialization recomputes instead (5.5 MiB vs 0.03 here)
    assert by["ild"]["temp_mib"] > by["forward"]["temp_mib"]
    assert by["ild_remat"]["temp_mib"] < 0.1 * by["ild"]["temp_mib"]
    assert r["chamfer_share_of_update_memory"] == pytest.approx(
        by["chamfer"]["temp_mib"] / by["ild"]["temp_mib"], rel=0.02, abs=2e-3)


def test_benchmark_set_times_the_task_config_with_fields_on_top(capsys):
    """`--set FIELD=VALUE` reaches the update the ild_task row times, under a name that
    says so: with remat=true the row keeps no backward residuals (as ild_remat, above);
    a field ILDConfig lacks, a bad value or a missing '=' is a usage error naming it."""
    from benchmarks.ild_speed import main, run
    plain, = run("pointmass", batch=4, repeats=1, with_apg=False, chunk=1, only=("ild_task",))
    remat, = run("pointmass", batch=4, repeats=1, with_apg=False, chunk=1, only=("ild_task",),
                 overrides={"remat": "true", "truncation": "128"})
    assert (plain["what"], remat["what"]) == ("ild_task", "ild_task:remat=true;truncation=128")
    assert remat["temp_mib"] < 0.1 * plain["temp_mib"]
    for bad, says in ((["bogus=1"], "no config field 'bogus'"), (["remat=maybe"], "expects bool"),
                      (["remat"], "--set expects key=value, got 'remat'")):
        with pytest.raises(SystemExit):
            main(["--task", "pointmass", "--rows", "ild_task", "--no-apg",
                  *[x for b in bad for x in ("--set", b)]])
        assert says in capsys.readouterr().err


def test_benchmark_memory_is_xla_working_memory():
    """temp_bytes is the compiled function's scratch: an (N, N) matmul result that is then
    summed must be materialized once (N * N float32 = 360,000 bytes for N = 300), while its
    (300, 200) argument is not counted."""
    from benchmarks.ild_speed import temp_bytes
    x = jnp.ones((300, 200))
    t = temp_bytes(jax.jit(lambda x: (x @ x.T).sum()).lower(x).compile())
    assert 300 * 300 * 4 <= t < 300 * 300 * 4 + 300 * 200 * 4


def test_benchmark_counts_the_page_faults_of_a_calls_working_memory():
    """XLA's CPU runtime maps a call's working memory afresh on every call: a (4096, 16) x
    (16, 4096) float32 product that is then summed needs a 64 MiB scratch result, and each
    timed call faults in its 16,384 pages of 4 KiB (64 MiB). This is the per-call cost that
    K updates in one scan pay once; if a jaxlib upgrade starts reusing
    the buffer, this fails and that finding needs re-measuring."""
    from benchmarks.ild_speed import _time
    x = jnp.ones((4096, 16))
    t = _time(lambda x: (x @ x.T).sum(), (x,), 3)
    assert 64 * 2**20 <= t.temp < 65 * 2**20  # the product, plus 64 KiB of XLA's own
    assert 63 <= t.fault_mib <= 72  # measured 65.4 MiB per call
    assert t.sys_s >= 0 and t.seconds > 0


def _lock_state(path) -> str:
    """'free', 'shared' (another process could share it) or 'exclusive', as seen from a
    second open file description of `path` (flock locks belong to those)."""
    import fcntl
    with open(path, "a") as f:
        for mode, name in ((fcntl.LOCK_EX, "free"), (fcntl.LOCK_SH, "shared")):
            try:
                fcntl.flock(f, mode | fcntl.LOCK_NB)
            except BlockingIOError:
                continue
            fcntl.flock(f, fcntl.LOCK_UN)
            return name
    return "exclusive"


def test_benchmark_times_under_the_time_lock(tmp_path, monkeypatch):
    """`--time-lock PATH`: each timed section holds an exclusive lock on PATH (several
    processes on one accelerator are then timed one at a time), compiling does not, and
    the lock is free again afterwards; a shared hold becomes exclusive on request; without
    a path nothing is locked."""
    from benchmarks import ild_speed as benchmark
    path = str(tmp_path / "lock")
    lock = benchmark.TimingLock(path)
    monkeypatch.setattr(benchmark, "TIME_LOCK", lock)
    seen = []
    callback = jax.debug.callback  # runs at each call of the compiled function, not at trace
    benchmark._time(lambda x: (callback(lambda: seen.append(_lock_state(path))), x + 1)[1],
                    (jnp.ones(3),), 2)
    assert seen == ["exclusive"] * 3  # the warm-up call and the 2 timed calls
    assert _lock_state(path) == "free"
    lock.acquire(shared=True)
    assert _lock_state(path) == "shared"
    lock.acquire()  # shared -> exclusive
    assert _lock_state(path) == "exclusive"
    lock.release()
    assert _lock_state(path) == "free"
    free = benchmark.TimingLock()  # no path: a no-op
    with free:
        assert free._file is None


def test_apg_epochs_leaves_out_the_two_warmup_epochs(monkeypatch):
    """apg_epochs runs brax's APG for 2 warm-up epochs + `rounds` (the first compiles; on
    JAX newer than the pin the second compiles again) and returns only the steady epochs'
    'training/sps'; `after_epoch` runs after every epoch, warm-up ones included. brax's
    train is faked: it reports an initial evaluation without sps, then one per epoch."""
    from brax.training.agents.apg import train as apg
    from benchmarks import ild_speed as benchmark
    seen, after = {}, []

    def fake_train(**kw):
        seen.update(kw)
        kw["progress_fn"](0, {"eval/episode_reward": 0.0})  # brax's first eval: no sps
        for it in range(1, kw["num_evals"]):
            kw["progress_fn"](it, {"training/sps": (23.0, 40.0, 4700.0, 4800.0)[it - 1]})
    monkeypatch.setattr(apg, "train", fake_train)
    task = make_task("pointmass")
    assert benchmark.apg_epochs(task, 4, (8,), 3, 2, after.append) == [4700.0, 4800.0]
    assert after == [1, 2, 3, 4]
    assert (seen["policy_updates"], seen["num_evals"], seen["num_envs"]) == (12, 5, 4)
    assert seen["horizon_length"] == task.episode_length
    with pytest.raises(ValueError, match="rounds=0"):
        benchmark.apg_epochs(task, 4, (8,), 3, 0)

    def short_train(**kw):
        kw["progress_fn"](1, {"training/sps": 1.0})
    monkeypatch.setattr(apg, "train", short_train)
    with pytest.raises(RuntimeError, match="for 1 epochs, expected 3"):
        benchmark.apg_epochs(task, 4, (8,), 3, 1)


def test_apg_is_timed_on_its_third_epoch_under_the_lock(tmp_path, monkeypatch):
    """brax's APG row: three epochs, the last one's steady-state env-steps/s (on newer JAX
    the second epoch compiles again: 23 env-steps/s against 4,700 on jax 0.10.2). The lock
    is held shared over the first two (they compile and run in one call of apg.train, so no
    other process's timed section may run beside them), exclusively over the third, and
    released at the end."""
    from benchmarks import ild_speed as benchmark
    path = str(tmp_path / "lock")
    monkeypatch.setattr(benchmark, "TIME_LOCK", benchmark.TimingLock(path))
    states = []

    def fake_apg(task, batch, hidden, updates, rounds, after_epoch):
        assert (batch, updates, rounds) == (8, 2, 1)
        sps = []
        for it in range(1, benchmark.APG_WARMUP_EPOCHS + rounds + 1):
            states.append(_lock_state(path))  # while epoch `it` runs
            sps.append(100.0 * it)
            after_epoch(it)
        return sps[benchmark.APG_WARMUP_EPOCHS:]
    monkeypatch.setattr(benchmark, "apg_epochs", fake_apg)
    assert benchmark._apg_sps(None, 8, (4,), 2) == 300.0
    assert states == ["shared", "shared", "exclusive"]
    assert _lock_state(path) == "free"


def test_benchmark_leaves_apg_out_where_the_reward_has_no_gradient():
    """APG descends minus the reward: on inverted_pendulum (a constant reward of 1 per step)
    its gradient is identically zero, XLA drops the backward pass, and its 'training/sps'
    (70k env-steps/s, the forward rollout's own) is no yardstick for ILD's update. pointmass's
    reward (minus the distance to the goal) has a gradient."""
    from benchmarks.ild_speed import reward_gradient_norm
    assert reward_gradient_norm(make_task("inverted_pendulum")) == 0.0
    assert reward_gradient_norm(make_task("pointmass")) > 0.1


def test_budget_lr_schedule_decays_over_the_budget_spent(store):
    """lr_schedule='budget' (the default): update k of 15 (env-step budget) runs at
    lr0 + k/15 (lr_end - lr0); 'linear' decays over `updates` (5000) and has barely moved
    after 15."""
    from methods.ild.train import budget_lr
    assert ILDConfig().lr_schedule == "budget"
    cfg = ILDConfig(lr_schedule="budget")
    assert budget_lr(cfg, 0.0) == 1e-3 and budget_lr(cfg, 1.0) == pytest.approx(1e-5)
    assert budget_lr(cfg, 0.5) == pytest.approx(0.505e-3)
    assert budget_lr(cfg, 7.0) == pytest.approx(1e-5)  # clipped at the end
    rec, _ = execute(prepare(_ild(0, bc_updates=0, lr_schedule="budget")), store,
                     log=lambda s: None)
    assert rec["status"] == "ok"
    assert rec["train_metrics"]["train/lr"] == pytest.approx(1e-3 + 14 / 15 * (1e-5 - 1e-3),
                                                             rel=1e-5)
    lin, _ = execute(prepare(_ild(0, bc_updates=0, lr_schedule="linear")), store,
                     log=lambda s: None)
    assert lin["train_metrics"]["train/lr"] == pytest.approx(1e-3 - 14 / 5000 * 0.99e-3,
                                                             rel=1e-5)


def test_negative_warmup_is_a_clear_error():
    with pytest.raises(ValueError, match="lr_warmup must be >= 0 updates, got -1"):
        ILDConfig(lr_warmup=-1)


@pytest.mark.parametrize("warmup", [0, 2])
def test_update_equals_optax_adam_on_the_same_gradient(warmup):
    """The update's optimizer (clip, Adam direction, then the scheduled step) is optax's
    clip + adam(schedule), step for step; with lr_warmup W the schedule is multiplied by
    min(1, (k + 1) / W) at update k."""
    import optax
    from methods.common.policy import ObsNorm, TanhGaussianPolicy
    from methods.ild.train import StateNorm, initial_state, make_rollout_loss, make_update
    task = make_task("pointmass")
    cfg = ILDConfig(num_envs=4, hidden=(16,), updates=3, lr_end=1e-4, lr_schedule="linear",
                    lr_warmup=warmup)
    policy = TanhGaussianPolicy(task.obs_size, task.action_size, cfg.hidden)
    goals = jnp.zeros((1, task.episode_length, task.state_size))
    norm = StateNorm(jnp.zeros(task.state_size), jnp.ones(task.state_size))
    params = policy.init(jax.random.PRNGKey(0), ObsNorm(jnp.zeros(task.obs_size),
                                                        jnp.ones(task.obs_size)))
    update, opt, lr = make_update(task, policy, goals, norm, cfg, jax.random.PRNGKey(1))
    loss_fn = make_rollout_loss(task, policy, goals, norm, cfg)
    sched = (lambda k: lr(k) * jnp.minimum(1.0, (k + 1) / warmup)) if warmup else lr
    ref = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(sched))
    s = initial_state(params, opt, jax.random.PRNGKey(2), cfg)
    p_ref, o_ref = params, ref.init(params)
    for _ in range(3):
        key, k_roll, k_init = jax.random.split(s.key, 3)
        g = jax.grad(lambda p: loss_fn(p, k_roll, jax.random.split(k_init, 4))[0])(p_ref)
        u, o_ref = ref.update(g, o_ref, p_ref)
        p_ref = optax.apply_updates(p_ref, u)
        s, _ = jax.jit(update)(s, None)
        for a, b in zip(jax.tree.leaves(s.params), jax.tree.leaves(p_ref)):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_inverted_pendulum_runs_full_bptt_by_task_override():
    from bench.plugins import build_config, get_method
    ild = get_method("ild")
    assert build_config(ild, "inverted_pendulum", "cpu").truncation == 128
    assert build_config(ild, "hopper", "cpu").truncation == 10


def test_a_plan_applies_its_rewrites_in_order_and_refuses_conflicts(monkeypatch):
    """`tasks.physics.apply` builds exactly the rewrites a plan names, in the order they
    compose: acrobot's plan runs the closed-form backward alone (it never reads brax's
    substeps), swimmer's rematerializes the substeps and then computes their small products
    as sums, brax's step as it is (`REFERENCE`) calls none. A plan with both whole-step and
    small-product rewrites is an error naming both. Planted fault: `apply` ignoring a field
    or applying small_dots before the rebuilt substep loop (which refuses such a copy)."""
    from tasks.physics import REFERENCE, Plan, apply, plan_for
    from tasks.physics import transforms
    calls = []
    for name in ("with_closed_form_adjoint", "with_small_dots", "with_substep_remat"):
        monkeypatch.setattr(transforms, name, lambda t, name=name: calls.append(name) or t)
    apply(make_task("acrobot"), plan_for("acrobot", "cpu"))
    assert calls == ["with_closed_form_adjoint"]
    calls.clear()
    apply(make_task("swimmer"), plan_for("swimmer", "cpu"))
    assert calls == ["with_substep_remat", "with_small_dots"]
    calls.clear()
    assert apply(make_task("swimmer"), REFERENCE) is make_task("swimmer") and calls == []
    with pytest.raises(ValueError, match="closed_form_adjoint differentiates.*small_dots"):
        Plan(closed_form_adjoint=True, small_dots=True)


@pytest.mark.slow
def test_full_bptt_is_closer_to_the_true_gradient_on_inverted_pendulum():
    """Why inverted_pendulum overrides truncation (methods/ild/config.py): from the BC warm
    start the update's gradient at truncation 128 (per-step normalization on) is closer to
    the true gradient than at truncation 10. Only the order is asserted: the cosines depend
    on round-off in the 1,000-step BC warm start, so on the CPU thread count (B = 16:
    one thread 0.869 at 10 vs 0.999 at 128, two threads 0.316 vs 0.781; -0.992 vs 1.000 at
    B = 32). ~7 minutes on the CPU (BC warm starts, full-BPTT compiles)."""
    from benchmarks.ild_probe import probe
    task = make_task("inverted_pendulum")
    demo = load_demo(task.spec.demo_path, task)
    short = probe(task, demo, ILDConfig(num_envs=16, truncation=10), eps=(1e-4,), lrs=(1e-5,))
    full = probe(task, demo, ILDConfig(num_envs=16, truncation=128), eps=(1e-4,), lrs=(1e-5,))
    assert full["loss"] == short["loss"]  # the same warm start and rollouts
    assert full["cosine"] > short["cosine"]


class _LossLog:
    """The smallest training context: records each report's metrics, never stops."""

    def __init__(self):
        self.reports = []

    def report(self, policy, env_steps, metrics, force_eval=False):
        self.reports.append(metrics)

    def should_stop(self, env_steps):
        return False

    def spent(self, env_steps):
        return 0.0

    def remaining(self, env_steps):
        return None, None


@pytest.mark.slow  # ~170 s, longer than any default test
def test_truncated_bptt_climbs_inverted_pendulums_loss_and_full_bptt_descends_it():
    """Why inverted_pendulum trains at truncation 128 (methods/ild/config.py), by training:
    40 ILD updates from the same BC warm start (B = 16, one update per call). At truncation
    10 the loss climbs from 0.0105 to ~3.4 and stays there (the pole falls); at 128 it
    settles at ~0.02 after Adam's first steps (one and two CPU threads alike:
    last ten updates 3.43 / 3.49 vs 0.021 / 0.016). ~90-140 s (two compiles)."""
    from methods.ild.train import train
    task = make_task("inverted_pendulum")
    demo = load_demo(task.spec.demo_path, task)
    losses = {}
    for t in (10, 128):
        log = _LossLog()
        train(task, demo, ILDConfig(num_envs=16, truncation=t, updates=40, chunk=1), log, 0)
        assert "bc/loss" in log.reports[0] and len(log.reports) == 41
        losses[t] = np.array([m["train/loss"] for m in log.reports[1:]])
    assert losses[10][0] == losses[128][0] < 0.05  # the same warm start and first rollouts
    short, full = losses[10][-10:].mean(), losses[128][-10:].mean()
    assert short > 1.0 and short > 30 * full
    assert full < 0.2 * losses[128].max()  # full BPTT recovers from its early spikes


def test_probe_without_joint_limits_lets_a_joint_pass_its_range():
    """`probe --no-joint-limits` (the swimmer finding, docs/methods/ild.md): the copy's
    cart, pushed at full force for 40 steps, runs past its slider's range [-1, 1]; the
    registry's task (left as it was) stops it there. pointmass has no limits: a clear error."""
    from tasks.core import without_joint_limits
    task = make_task("inverted_pendulum")
    free = without_joint_limits(task)
    assert task.env.unwrapped.sys.dof.limit is not None and free.env is not task.env

    def pushed(t):
        def body(s, _):
            return t.env.step(s, jnp.ones(t.action_size)), None
        s = jax.lax.scan(body, t.env.reset(jax.random.PRNGKey(0)), None, length=40)[0]
        return float(s.pipeline_state.q[0])

    assert pushed(task) < 1.05 and pushed(free) > 1.5
    with pytest.raises(ValueError, match="no brax joint limits"):
        without_joint_limits(make_task("pointmass"))


def test_ild_joint_limits_off_differentiates_through_the_limitless_copy(monkeypatch):
    """ILDConfig.joint_limits=False hands the update the copy without limits (the rollouts'
    physics) and leaves the task itself alone; on a task without limits it says so."""
    import importlib
    ild_train = importlib.import_module("methods.ild.train")  # the module, not the function
    seen = []

    def spy(task, *args, **kw):
        seen.append(task)
        raise RuntimeError("stop after make_update")

    monkeypatch.setattr(ild_train, "make_update", spy)
    task = make_task("inverted_pendulum")
    demo = load_demo(task.spec.demo_path, task)
    for limits in (True, False):
        with pytest.raises(RuntimeError, match="stop after"):
            ild_train.train(task, demo, _cfg(joint_limits=limits, bc_updates=0), None, 0)
    # with limits the task as handed (its physics plan is the view's business), without
    # them a copy with a limitless system
    assert seen[0] is task and seen[1] is not task
    assert seen[1].env.unwrapped.sys.dof.limit is None
    assert task.env.unwrapped.sys.dof.limit is not None
    point = make_task("pointmass")
    with pytest.raises(ValueError, match="no brax joint limits"):
        ild_train.train(point, load_demo(point.spec.demo_path, point),
                        _cfg(joint_limits=False, bc_updates=0), None, 0)


def test_probe_finite_differences_match_the_gradient_where_the_loss_is_smooth():
    """benchmarks.ild_probe on pointmass (linear dynamics, no contacts): central differences at
    eps 1e-3 equal the analytic directional derivative, and Adam's first step at a tiny lr
    lowers the loss (a descent direction), at a huge one raises it."""
    from benchmarks.ild_probe import probe
    task = make_task("pointmass")
    demo = load_demo(task.spec.demo_path, task)
    r = probe(task, demo, _cfg(bc_updates=20), eps=(1e-3,), lrs=(1e-7, 1.0))
    np.testing.assert_allclose(r["fd"][1e-3], r["grad_norm"], rtol=0.05)
    assert r["adam"][1e-7] < r["loss"] < r["adam"][1.0]
    assert -1.0 <= r["cosine"] <= 1.0 and set(r["adam_used"]) == {1e-7, 1.0}
    full = probe(task, demo, _cfg(bc_updates=20, truncation=task.episode_length,
                                  grad_normalization=False), eps=(1e-3,), lrs=(1e-7,))
    assert full["cosine"] == pytest.approx(1.0, abs=1e-5)  # the update's gradient is the true one
    assert full["adam_used"][1e-7] == pytest.approx(full["adam"][1e-7], rel=1e-6)
    # what the per-step normalizer saw: the action's and the next state's cotangent per env
    # and step (B = 4); none without the normalizer
    c = r["cotangents"]
    assert c["count"] == 2 * task.episode_length * 4 and c["max"] > 0
    assert 0.0 <= c["clipped"] <= 1.0 and (c["clipped"] > 0) == (c["max"] > 1)
    assert full["cotangents"] == {"count": 0, "max": 0.0, "clipped": 0.0}
    assert r["params"] == sum(x.size for x in jax.tree_util.tree_leaves(
        TanhGaussianPolicy(task.obs_size, task.action_size, (32, 32)).init(
            jax.random.PRNGKey(0), ObsNorm.fit(jnp.zeros((2, task.obs_size))))["net"]))


@pytest.mark.slow  # two step gradients compiled; the default run checks substep remat
# inside the lean and hand-adjoint substeps (tests/test_lean_substeps.py)
def test_substep_remat_computes_the_same_physics_and_gradient():
    """with_substep_remat (substep_remat=True) checkpoints each brax substep inside a control
    step: the same states and the same gradient through 3 steps (acrobot: brax's generalized
    pipeline, 4 substeps per step), to float32 round-off, with less of the backward pass's
    working memory; the registry's cached task keeps brax's own pipeline_step."""
    from benchmarks.ild_speed import temp_bytes
    from tasks.core import open_loop
    from tasks.physics.transforms import with_substep_remat
    task = make_task("acrobot")
    sub = with_substep_remat(task)
    assert sub.env.unwrapped is not task.env.unwrapped
    assert "pipeline_step" not in vars(task.env.unwrapped)  # the cached env is untouched
    s0 = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), 4))
    acts = 0.5 * jax.random.normal(jax.random.PRNGKey(1), (3, 4, task.action_size))

    def total(t):
        def f(a):
            _, m = open_loop(jax.vmap(t.env.step), s0, a, jax.vmap(t.matched_state))
            return jnp.sum(jnp.sin(m))
        return f

    vjp = {n: jax.jit(jax.value_and_grad(total(t))) for n, t in (("brax", task), ("sub", sub))}
    (v0, g0), (v1, g1) = vjp["brax"](acts), vjp["sub"](acts)
    assert float(v0) == pytest.approx(float(v1), rel=1e-6)
    np.testing.assert_allclose(g1, g0, rtol=1e-4, atol=1e-6)
    assert float(jnp.abs(g0).sum()) > 0
    remat = jax.make_jaxpr(jax.checkpoint(jnp.sin))(1.0).eqns[0].primitive.name + "["
    assert remat in str(jax.make_jaxpr(total(sub))(acts))
    assert remat not in str(jax.make_jaxpr(total(task))(acts))
    mem = {n: temp_bytes(f.lower(acts).compile()) for n, f in vjp.items()}
    assert mem["sub"] < mem["brax"]


def test_substep_remat_keeps_a_joint_limit_free_copy_and_refuses_non_brax_tasks():
    from tasks.core import without_joint_limits
    from tasks.physics.transforms import with_substep_remat
    swimmer = make_task("swimmer")
    assert swimmer.env.unwrapped.sys.dof.limit is not None
    both = with_substep_remat(without_joint_limits(swimmer))
    assert both.env.unwrapped.sys.dof.limit is None
    assert make_task("swimmer").env.unwrapped.sys.dof.limit is not None
    with pytest.raises(ValueError, match="pointmass.*substep_remat"):
        with_substep_remat(make_task("pointmass"))


def test_plan_rematerializes_brax_substeps_and_leaves_other_steps_alone():
    """`Plan()` rematerializes each brax substep: on hopper its physics is a
    with_substep_remat copy (its own pipeline_step, checkpointed); `REFERENCE` keeps brax's;
    pointmass has no substep loop, so the plan leaves its task as it is instead of refusing
    it."""
    from tasks.core import has_substep_loop
    from tasks.physics import REFERENCE, Plan, apply
    hopper, pointmass = make_task("hopper"), make_task("pointmass")
    assert has_substep_loop(hopper) and not has_substep_loop(pointmass)
    phys = apply(hopper, Plan())
    assert phys is not hopper and "pipeline_step" in vars(phys.env.unwrapped)
    assert apply(hopper, REFERENCE) is hopper
    assert apply(pointmass, Plan()) is pointmass


def test_speed_benchmark_runs_the_rows_asked_for():
    from benchmarks.ild_speed import run
    rows = run("pointmass", batch=4, repeats=1, with_apg=False, chunk=2,
               only=("forward", "ild_substep", "ild_both", "ild_substep_chunk", "dots"))
    assert [r["what"] for r in rows] == ["forward"]  # pointmass has no brax pipeline
    with pytest.raises(ValueError, match="unknown benchmark rows.*'nope'"):
        run("pointmass", batch=4, repeats=1, with_apg=False, only=("forward", "nope"))


def test_speed_benchmark_ild_task_row_is_the_config_the_task_trains_with(monkeypatch):
    """`ild_task` times ILD's update as the task trains (class defaults + TASK_OVERRIDES, at
    the benchmark's batch): acrobot's closed form with full BPTT, swimmer's small dots,
    hopper's lean substeps, hand-written VJPs, hinge forces and planar root and the planar adjoint,
    pointmass's the `ild` row's own config, whose timing it then reports again rather than
    compiling the same update twice."""
    from benchmarks import ild_speed as benchmark
    from tasks.physics import Plan
    Setup = benchmark.Setup
    acro = benchmark.task_config("acrobot", 8)
    assert acro == Setup(ILDConfig(num_envs=8, truncation=128), Plan(closed_form_adjoint=True))
    assert benchmark.task_config("swimmer", 8) == Setup(ILDConfig(num_envs=8),
                                                        Plan(small_dots=True))
    assert benchmark.task_config("hopper", 8) == Setup(ILDConfig(num_envs=8), Plan(
        lean_substeps=True, hand_adjoint=True, hinge_forces=True, planar_root=True,
        planar_adjoint=True, planar_links=True))
    assert benchmark.task_config("pointmass", 8) == Setup(ILDConfig(num_envs=8))
    # turning hand_adjoint off turns its pieces off with it
    xla = benchmark.task_config("hopper", 8, {"hand_adjoint": "false"})
    assert not (xla.hand_adjoint or xla.hinge_forces or xla.planar_root) and xla.lean_substeps
    compiled = []
    real = benchmark.make_update
    monkeypatch.setattr(benchmark, "make_update",
                        lambda *a, **k: compiled.append(a[4]) or real(*a, **k))
    rows = benchmark.run("pointmass", batch=2, repeats=1, with_apg=False,
                         only=("forward", "ild", "ild_task"))
    assert [r["what"] for r in rows] == ["forward", "ild", "ild_task"]
    assert compiled == [ILDConfig(num_envs=2)]
    assert rows[1]["seconds"] == rows[2]["seconds"]
    assert rows[2]["task_update_over_forward"] == round(rows[1]["seconds"]
                                                        / rows[0]["seconds"], 3)


@pytest.mark.slow  # benchmark tool
def test_speed_benchmark_times_apg_on_small_dots_physics_alone(apg_timed):
    """'dots' is four rows, each a group of its own: a GPU call times ild_substep_dots in the
    ILD process and apg_dots in the APG process. apg_dots alone runs brax's APG on the
    rewritten physics (`with_small_dots`: the env's pipeline_step replaced) and nothing
    else; apg runs it on brax's own; pointmass (no brax step) leaves the dots rows out."""
    from benchmarks import ild_speed as benchmark
    assert benchmark.expand_rows(("forward", "dots", "apg_dots", "apg")) == (
        "forward", "forward_dots", "ild_dots", "ild_substep_dots", "apg_dots", "apg")
    assert benchmark.expand_rows(("ild_substep_dots",)) == ("ild_substep_dots",)
    timed = apg_timed
    rows = benchmark.run("hopper", batch=2, repeats=3, only=("apg_dots",))
    assert [r["what"] for r in rows] == ["apg_dots"] and timed == [True]
    assert rows[0]["seconds"] == pytest.approx(2 * 128 / 1000.0)
    rows = benchmark.run("hopper", batch=2, repeats=3, only=("apg", "apg_dots"))
    assert [r["what"] for r in rows] == ["apg", "apg_dots"] and timed == [True, False, True]
    assert benchmark.run("pointmass", batch=2, repeats=1, with_apg=False,
                         only=("apg_dots", "ild_substep_dots")) == []
    with pytest.raises(ValueError, match="unknown benchmark rows.*'apg_dot'"):
        benchmark.run("hopper", batch=2, repeats=1, only=("apg_dot",))


def test_speed_benchmark_times_apg_through_the_closed_form_backward(apg_timed):
    """'closed_form' is two rows, each a group of its own: apg_closed_form runs brax's APG on
    acrobot's closed-form-adjoint physics (like with like for ild_closed_form); tasks with
    no closed-form step (hopper) leave both rows out."""
    from benchmarks import ild_speed as benchmark
    assert benchmark.expand_rows(("closed_form", "apg")) == (
        "ild_closed_form", "apg_closed_form", "apg")
    timed = apg_timed
    rows = benchmark.run("acrobot", batch=2, repeats=3, only=("apg", "apg_closed_form"))
    assert [r["what"] for r in rows] == ["apg", "apg_closed_form"] and timed == [False, True]
    assert benchmark.run("hopper", batch=2, repeats=1, only=("closed_form",)) == []


def test_speed_benchmark_csv_names_the_xla_flags(tmp_path, monkeypatch):
    # Rows timed under another XLA code generator are not comparable: the CSV says which.
    import pandas as pd
    from benchmarks.ild_speed import main
    out = str(tmp_path / "speed.csv")
    args = ["--task", "pointmass", "--batch", "4", "--repeats", "1", "--no-apg",
            "--rows", "forward", "--out", out]
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.delenv("GLIBC_TUNABLES", raising=False)
    main(args)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.hugetlb=1")  # bench.malloc
    main(args)
    rows = pd.read_csv(out)
    assert list(rows.what) == ["forward", "forward"]
    assert rows.xla_flags.isna().tolist() == [True, False]
    assert rows.xla_flags.iloc[1] == "--xla_cpu_use_fusion_emitters=false"
    assert rows.malloc_hugetlb.isna().tolist() == [True, False]
    assert rows.malloc_hugetlb.iloc[1] == 1


def test_paired_summary_takes_medians_over_rounds_and_the_fastest_rounds_ratio(tmp_path,
                                                                             capsys):
    """benchmarks.ild_paired's summary, on hand-made rows: medians over rounds of the seconds
    and of the per-round ratios, their ranges, and update / forward from the fastest rounds
    (fastest update over fastest forward, here from different rounds); rows without the
    forward (NaN in a CSV) get no forward figures; a second variant gets its speed-up over
    the first from the rounds both ran. `--summarize` reads an earlier run's CSV
    and refuses a file that is not one, naming it."""
    import pandas as pd
    from benchmarks import ild_paired as paired
    rows = [{"task": "hopper", "variant": "task", "round": i, "seconds": s, "apg_seconds": a,
             "over_apg": round(a / s, 3), "forward_seconds": f, "over_forward": round(s / f, 3)}
            for i, (s, a, f) in enumerate([(0.30, 0.60, 0.10), (0.20, 0.50, 0.08),
                                           (0.25, 0.40, 0.05)])]
    rows += [{"task": "hopper", "variant": "old", "round": i, "seconds": s,
              "apg_seconds": 0.6, "over_apg": 1.5, "forward_seconds": float("nan"),
              "over_forward": float("nan")} for i, s in ((0, 0.4), (2, 0.2))]
    task, old = paired.summarize(rows)
    # old against the first variant, task, round by round: 0.30 / 0.4 and 0.25 / 0.2
    assert (old["speedup"], old["speedup_min"], old["speedup_max"]) == pytest.approx(
        (1.0, 0.75, 1.25)) and old["speedup_over"] == "task" and "speedup" not in task
    assert (task["rounds"], task["seconds"], task["apg_seconds"]) == (3, 0.25, 0.5)
    assert (task["over_apg"], task["over_apg_min"], task["over_apg_max"]) == (2.0, 1.6, 2.5)
    assert (task["over_forward"], task["over_forward_min"], task["over_forward_max"]) == (
        3.0, 2.5, 5.0)
    assert task["forward_seconds"] == 0.08
    assert task["fastest_over_forward"] == pytest.approx(0.20 / 0.05)
    assert old["rounds"] == 2 and "over_forward" not in old and old["over_apg"] == 1.5
    path = tmp_path / "paired.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    paired.main(["--summarize", str(path)])
    out = capsys.readouterr().out.splitlines()
    assert out == paired.summary_lines(rows) and "fastest rounds 4.000 over 3 rounds" in out[0]
    assert out[1].endswith("over 2 rounds; 1.000x as fast as task [0.750, 1.250]")
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    with pytest.raises(SystemExit):
        paired.main(["--summarize", str(tmp_path / "other.csv")])
    assert "other.csv: not rows of benchmarks.ild_paired" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        paired.main(["--task", "hopper"])
    assert "--variant is required" in capsys.readouterr().err


@pytest.mark.slow  # benchmark tool
def test_paired_times_each_variant_between_apg_epochs(monkeypatch):
    """benchmarks.ild_paired: every variant is timed once between two of APG's epochs and
    each round's ratio is APG's seconds per update over the variant's, from that round; APG's
    first two epochs (compiles, on newer JAX both) are no round. Without APG (`apg=False`,
    `--apg-physics none`) the variants run round after round, a first round left out."""
    from benchmarks import ild_paired as paired
    from benchmarks.ild_speed import APG_WARMUP_EPOCHS
    calls = []

    def fake_apg(task, batch, hidden, updates, rounds, after_epoch):
        for it in range(1, APG_WARMUP_EPOCHS + rounds + 1):  # after the warm-up epochs too
            calls.append(it)
            after_epoch(it)
        return [batch * 128 / s for s in (0.5, 0.25)]  # the steady epochs only

    monkeypatch.setattr(paired, "apg_epochs", fake_apg)
    monkeypatch.setattr(paired, "reward_gradient_norm", lambda task: 1.0)
    rows = paired.run("pointmass", ["chunk=2", "remat"], batch=4, rounds=2, repeats=3)
    assert calls == [1, 2, 3, 4]
    assert {r["apg_physics"] for r in rows} == {"brax"}
    import os
    from bench.malloc import hugetlb
    assert {r["malloc_hugetlb"] for r in rows} == {hugetlb(os.environ)}
    assert [(r["variant"], r["round"]) for r in rows] == [
        ("chunk=2", 0), ("chunk=2", 1), ("remat", 0), ("remat", 1)]
    for r in rows:
        assert r["apg_seconds"] == (0.5, 0.25)[r["round"]]
        assert r["over_apg"] == pytest.approx(r["apg_seconds"] / r["seconds"], rel=2e-3)
        assert 0 < r["seconds"] < 10
        assert "over_forward" not in r
    # --forward: the forward rollout timed in every round, each row's ratio from its round
    calls.clear()
    rows = paired.run("pointmass", ["chunk=2"], batch=4, rounds=2, repeats=3, forward=True)
    assert calls == [1, 2, 3, 4] and len(rows) == 2
    for r in rows:
        assert 0 < r["forward_seconds"] < r["seconds"]  # no gradient: cheaper than an update
        assert r["over_forward"] == pytest.approx(r["seconds"] / r["forward_seconds"],
                                                  rel=2e-3)
    cfg = paired.parse_variant("substep_remat,chunk=4,truncation=5", 8)
    assert (cfg.substep_remat, cfg.chunk, cfg.truncation, cfg.num_envs) == (True, 4, 5, 8)
    from bench.plugins import ConfigError
    with pytest.raises(ConfigError, match="no config field 'nope'"):
        paired.parse_variant("nope", 8)
    monkeypatch.setattr(paired, "reward_gradient_norm", lambda task: 0.0)
    with pytest.raises(ValueError, match="'pointmass'.*no gradient.*--apg-physics none"):
        paired.run("pointmass", ["chunk=2"], batch=4, rounds=1, repeats=1)
    # --apg-physics none: no APG epoch, the variants and the forward alone, one warm-up round
    calls.clear()
    rows = paired.run("pointmass", ["chunk=2", "remat"], batch=4, rounds=2, repeats=3,
                      forward=True, apg=False)
    assert calls == [] and [(r["variant"], r["round"]) for r in rows] == [
        ("chunk=2", 0), ("chunk=2", 1), ("remat", 0), ("remat", 1)]
    assert all(r["apg_physics"] == "none" and r["apg_seconds"] != r["apg_seconds"]
               and 0 < r["forward_seconds"] < r["seconds"] for r in rows)
    line = paired.summary_lines(rows)[1]
    assert "APG" not in line and "update / forward" in line and "as fast as chunk=2" in line
    for variants, match in (
            (["chunk=2", "hidden=[64]"], r"'hidden=\[64\]' sets hidden=\(64,\).*one network"),
            (["num_envs=64"], r"'num_envs=64' sets num_envs=64.*--batch \(now 4\)"),
            (["small_dots", "remat"], r"\['small_dots'\] set small_dots and \['remat'\]"),
            (["closed_form_adjoint", "chunk=2"],
             r"\['closed_form_adjoint'\] set closed_form_adjoint and \['chunk=2'\]")):
        with pytest.raises(ValueError, match=match):  # refused before any task is built
            paired.run("no_such_task", variants, batch=4, rounds=1, repeats=1)
    base = paired.Setup(paired.ILDConfig(num_envs=4))
    assert paired.apg_physics({v: paired.parse_variant(v, 4) for v in
                               ("small_dots", "small_dots,chunk=2")}, base) == "small_dots"
    assert paired.apg_physics({v: paired.parse_variant(v, 4) for v in
                               ("closed_form_adjoint", "closed_form_adjoint,chunk=2")},
                              base) == "closed_form_adjoint"
    assert paired.apg_physics({"chunk=2": paired.parse_variant("chunk=2", 4)}, base) == "brax"
    # 'task' starts from the task's TASK_OVERRIDES; --apg-physics brax allows any mix and
    # times brax's APG as shipped
    from tasks.physics import Plan
    assert paired.parse_variant("task", 4, "acrobot") == paired.Setup(
        paired.ILDConfig(num_envs=4, truncation=128), Plan(closed_form_adjoint=True))
    assert paired.parse_variant("task,chunk=2", 4, "swimmer") == paired.Setup(
        paired.ILDConfig(num_envs=4, chunk=2), Plan(small_dots=True))
    assert paired.parse_variant("chunk=2", 4, "acrobot") == paired.Setup(
        paired.ILDConfig(num_envs=4, chunk=2))
    mixed = {v: paired.parse_variant(v, 4, "acrobot") for v in ("task", "chunk=2")}
    with pytest.raises(ValueError, match="--apg-physics brax"):
        paired.apg_physics(mixed, base)
    assert paired.apg_physics(mixed, base, brax=True) == "brax"
    assert paired.apg_physics({"task": mixed["task"]}, base) == "closed_form_adjoint"


@pytest.mark.slow  # two gradient compiles per task
@pytest.mark.parametrize("task_name", ["ant", "hopper", "humanoid", "reacher", "walker2d",
                                       "swimmer", "inverted_pendulum", "acrobot"])
def test_kernel_grad_group_is_the_same_gradient_to_round_off_on_every_brax_task(task_name):
    """kernel_grad_group=8 on the paper's 8 tasks, each with the config it trains with (its
    TASK_OVERRIDES), at B = 8 over a 16-step episode (two groups): the rollout loss and
    every gradient leaf equal G = 1's to float32 round-off, within 1e-3 of the leaf's
    largest entry. That is the spread of two programs of one function: whole-step `remat`
    moves humanoid's gradient by 4.5e-4 of a leaf's largest entry, G = 8 by 2.2e-4; a lost
    group or a misplaced factor moves it by order 1. Over the full 128 steps the contact
    tasks' float32 rollouts differ between any two compiled programs (ant's G = 1 loss
    2.7095 in its forward program, 2.7183 in its value_and_grad: round-off the contacts
    amplify), so the comparison there would test chaos, not the grouping
   ."""
    from benchmarks.ild_speed import speed_setup, task_config
    from tasks.core import Task
    task = make_task(task_name)
    task = Task(spec=dataclasses.replace(task.spec, episode_length=16), env=task.env)
    out = {}
    for group in (1, 8):
        cfg = task_config(task_name, 8, {"kernel_grad_group": group})
        policy, goals, norm, params, k = speed_setup(task, cfg)
        loss = make_rollout_loss(cfg.physics(task), policy, goals, norm, cfg.config)
        init_keys = jax.random.split(k[2], 8)
        out[group] = jax.jit(jax.value_and_grad(
            lambda p: loss(p, k[3], init_keys)[0]))(params)
    np.testing.assert_allclose(float(out[8][0]), float(out[1][0]), rtol=1e-5)
    flat = jax.tree_util.tree_flatten_with_path(out[1][1])[0]
    for (path, a), b in zip(flat, jax.tree_util.tree_leaves(out[8][1])):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-3 * float(jnp.abs(a).max()),
                                   err_msg=jax.tree_util.keystr(path))
    assert float(jnp.abs(out[1][1]["net"]["params"]["hidden_1"]["kernel"]).sum()) > 0


@pytest.mark.slow  # two update compiles per task: 1-3 minutes each on one CPU core
@pytest.mark.parametrize("task_name", ["ant", "hopper", "humanoid", "reacher", "walker2d",
                                       "swimmer", "inverted_pendulum", "acrobot"])
def test_swish_remat_is_the_same_update_bit_for_bit_on_every_brax_task(task_name):
    """swish_remat's claim on the paper's 8 tasks, each with the config it trains with (its
    TASK_OVERRIDES: hand-written VJPs, closed form, small dots) at B = 8: the parameters and
    metrics after one update equal swish_remat=False's bit for bit."""
    from benchmarks.ild_speed import speed_setup, task_config
    from benchmarks.ild_paired import compiled_chunk
    task = make_task(task_name)
    after = {}
    for remat in (False, True):
        cfg = task_config(task_name, 8, {"swish_remat": remat})
        assert cfg.swish_remat is remat
        chunk, state, n = compiled_chunk(task, cfg, speed_setup(task, cfg))
        after[remat] = chunk(state, n)
    for a, b in zip(jax.tree_util.tree_leaves(after[False]),
                    jax.tree_util.tree_leaves(after[True])):
        np.testing.assert_array_equal(b, a)
    assert float(after[True][1]["grad/norm_raw"][0]) > 0
