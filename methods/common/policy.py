"""The paper's policy (A.5): MLP 512-256 with swish, lecun-uniform init, and a tanh-Gaussian
head (std = softplus(s) + 0.001, action = tanh(loc + std * eps), reparameterized); built
from brax's own network and distribution classes. Observations are normalized with fixed
statistics (mean, std with variance clipped to [std_min^2, 1e6], output clipped to +/-5, as
the original code's normalizer, which used std_min = 1e-3)."""
from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import optax
import tasks  # noqa: F401  (before brax: tasks/__init__.py keeps brax's import noise quiet)
from brax.training import distribution, networks
from flax import linen


@dataclasses.dataclass(frozen=True)
class ObsNorm:
    mean: jax.Array
    std: jax.Array

    @staticmethod
    def fit(obs: jax.Array, std_min: float = 1e-3) -> "ObsNorm":
        """Statistics of `obs` (..., D). `std_min` floors the std: one demo often barely
        varies some features, and dividing test-time deviations by that tiny spread throws
        the network far outside what it was fit on."""
        obs = jnp.reshape(obs, (-1, obs.shape[-1]))
        var = jnp.clip(jnp.var(obs, axis=0), std_min ** 2, 1e6)
        return ObsNorm(mean=jnp.mean(obs, axis=0), std=jnp.sqrt(var))

    def __call__(self, obs: jax.Array) -> jax.Array:
        return jnp.clip((obs - self.mean) / self.std, -5.0, 5.0)


jax.tree_util.register_dataclass(ObsNorm, data_fields=["mean", "std"], meta_fields=[])


def _product(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """x @ kernel for x of shape (..., in): the forward product of `dense_t` and
    `swish_dense_t`."""
    return jax.lax.dot_general(x, kernel, (((x.ndim - 1,), (0,)), ((), ())))


def contract_leading(x: jax.Array, g: jax.Array) -> jax.Array:
    """x^T g over every leading axis: a kernel's cotangent from its input and output's."""
    return jax.lax.dot_general(x, g, ((tuple(range(x.ndim - 1)),) * 2, ((), ())))


@jax.custom_vjp
def dense_t(x: jax.Array, kernel: jax.Array, kernel_t: jax.Array) -> jax.Array:
    """x @ kernel (flax Dense's product) for x of shape (..., in), whose backward computes
    x's cotangent as g @ kernel_t, with kernel_t = kernel.T made once outside the rollout's
    loop (it gets no cotangent), and kernel's as one product over all leading axes of x.
    XLA's CPU backend runs g @ kernel.T, the product reverse mode otherwise emits, at about
    half the speed of g @ kernel_t."""
    return _product(x, kernel)


def _dense_t_fwd(x, kernel, kernel_t):
    return dense_t(x, kernel, kernel_t), (x, kernel_t)


def _dense_t_bwd(res, g):
    x, kernel_t = res
    return g @ kernel_t, contract_leading(x, g), None


dense_t.defvjp(_dense_t_fwd, _dense_t_bwd)


ACTIVATION = linen.swish
"""The hidden layers' activation (A.5): brax's network and `sample_batch` both use it."""


@jax.custom_vjp
def swish_dense_t(h: jax.Array, kernel: jax.Array, kernel_t: jax.Array) -> jax.Array:
    """swish(h) @ kernel: a hidden layer's activation and the next layer's product, whose
    backward keeps only the pre-activation h and recomputes sigmoid(h) and swish(h) from it.
    Reverse mode of the two apart keeps swish's intermediates and its output (four floats per
    hidden unit, most of hopper's update's working memory at B = 32), which a rollout's scan
    stacks over its 128 steps; writing and reading them
    costs more than the sigmoid again. The backward computes reverse mode's own expressions
    (swish's cotangent g*s + (g*h)*(s*(1-s)), the kernel's x^T g and x's g @ kernel_t), so
    the gradient is the same bit for bit (tests/test_ild.py: alone, on pointmass's rollout,
    and, behind -m slow, one update of each of the 8 brax tasks)."""
    return _product(ACTIVATION(h), kernel)


def _swish_dense_t_fwd(h, kernel, kernel_t):
    return swish_dense_t(h, kernel, kernel_t), (h, kernel_t)


def _swish_backward(h: jax.Array, kernel_t: jax.Array, g: jax.Array):
    """swish(h) @ kernel's backward from the pre-activation h alone: (h's cotangent,
    swish(h)), the second the kernel cotangent's input factor."""
    s = jax.nn.sigmoid(h)
    gx = g @ kernel_t
    # swish = h * sigmoid(h): the product's two cotangents, sigmoid's through s * (1 - s)
    return gx * s + (gx * h) * (s * (1 - s)), h * s


def _swish_dense_t_bwd(res, g):
    h, kernel_t = res
    ct_h, swish = _swish_backward(h, kernel_t, g)
    return ct_h, contract_leading(swish, g), None


swish_dense_t.defvjp(_swish_dense_t_fwd, _swish_dense_t_bwd)


@jax.custom_vjp
def dense_tap(x: jax.Array, kernel: jax.Array, kernel_t: jax.Array, tap) -> jax.Array:
    """x @ kernel, like `dense_t`, whose backward does not make the kernel's cotangent: it
    hands that product's two factors out as the cotangent of `tap` (zeros shaped like x and
    like the output), (x, g), so that the caller can multiply them for many steps at once
    (`ILDConfig.kernel_grad_group`)."""
    return _product(x, kernel)


def _dense_tap_fwd(x, kernel, kernel_t, tap):
    return dense_tap(x, kernel, kernel_t, tap), (x, kernel_t)


def _dense_tap_bwd(res, g):
    x, kernel_t = res
    return g @ kernel_t, None, None, (x, g)


dense_tap.defvjp(_dense_tap_fwd, _dense_tap_bwd)


@jax.custom_vjp
def swish_dense_tap(h: jax.Array, kernel: jax.Array, kernel_t: jax.Array, tap) -> jax.Array:
    """swish(h) @ kernel, like `swish_dense_t`, whose backward hands the kernel's cotangent's
    factors (swish(h), g) out through `tap`'s cotangent instead of multiplying them."""
    return _product(ACTIVATION(h), kernel)


def _swish_dense_tap_fwd(h, kernel, kernel_t, tap):
    return swish_dense_tap(h, kernel, kernel_t, tap), (h, kernel_t)


def _swish_dense_tap_bwd(res, g):
    h, kernel_t = res
    ct_h, swish = _swish_backward(h, kernel_t, g)
    return ct_h, None, None, (swish, g)


swish_dense_tap.defvjp(_swish_dense_tap_fwd, _swish_dense_tap_bwd)


@dataclasses.dataclass(frozen=True)
class TanhGaussianPolicy:
    obs_size: int
    action_size: int
    hidden: Sequence[int] = (512, 256)

    @property
    def _dist(self):
        return distribution.NormalTanhDistribution(event_size=self.action_size, min_std=0.001)

    @property
    def _net(self):
        return networks.make_policy_network(
            self._dist.param_size, self.obs_size, hidden_layer_sizes=tuple(self.hidden),
            activation=ACTIVATION)

    def init(self, key: jax.Array, norm: ObsNorm) -> dict:
        return {"net": self._net.init(key), "norm": norm}

    def logits(self, params: dict, obs: jax.Array) -> jax.Array:
        # The normalizer's statistics are fixed: they sit in `params` so that a saved policy
        # carries them, but no optimizer may move them (before ildbench bc v2 / ild v4 they
        # got gradients, and BC's 1000 Adam steps moved hopper's std floor of 1.0 to 0.81).
        norm = jax.lax.stop_gradient(params["norm"])
        return self._net.apply(None, params["net"], norm(obs))

    def kernels_t(self, params: dict) -> tuple[jax.Array, ...]:
        """The network's kernels transposed, without gradient: `sample_batch`'s fast backward
        (make them once, outside a rollout's loop)."""
        layers = params["net"]["params"]
        return tuple(jax.lax.stop_gradient(layers[f"hidden_{i}"]["kernel"].T)
                     for i in range(len(layers)))

    def zero_taps(self, lead: tuple, dtype=jnp.float32) -> tuple:
        """Zero taps for `sample_batch(taps=...)`: per layer, zeros shaped like its input and
        its output, with leading axes `lead` (`dtype`: the network's)."""
        sizes = (self.obs_size, *self.hidden, self._dist.param_size)
        return tuple((jnp.zeros((*lead, i), dtype), jnp.zeros((*lead, o), dtype))
                     for i, o in zip(sizes[:-1], sizes[1:]))

    def sample_batch(self, params: dict, obs: jax.Array, keys: jax.Array,
                     kernels_t: tuple[jax.Array, ...], swish_remat: bool = True,
                     taps: tuple | None = None) -> jax.Array:
        """`sample` for a batch: obs (B, obs_size), keys (B, 2) -> (B, action_size), the
        same values as vmap(sample); the network's products run through `dense_t`, so the
        backward reads `kernels_t` (from `kernels_t(params)`) instead of transposing every
        kernel at every step. Batched on purpose: under vmap, the kernels' cotangents would
        be made per example and then summed. `swish_remat`: each hidden activation and the
        product after it as one `swish_dense_t`, whose backward keeps only the
        pre-activation (the same values and gradient bit for bit, fewer residuals). `taps`
        (`zero_taps((B,))`): the layers run as `dense_tap` / `swish_dense_tap`, whose
        backward hands each kernel's cotangent's factors out through the taps' cotangents
        and gives the kernels none (`ILDConfig.kernel_grad_group`)."""
        layers = params["net"]["params"]
        x = jax.lax.stop_gradient(params["norm"])(obs)
        for i, kt in enumerate(kernels_t):
            layer = layers[f"hidden_{i}"]
            if taps is not None:  # the kernels' cotangent factors out through the taps
                fn = dense_tap if i == 0 or not swish_remat else swish_dense_tap
                x = x if i == 0 or swish_remat else ACTIVATION(x)
                x = fn(x, layer["kernel"], kt, taps[i])
            elif i == 0:
                x = dense_t(x, layer["kernel"], kt)
            elif swish_remat:  # x is the previous layer's pre-activation
                x = swish_dense_t(x, layer["kernel"], kt)
            else:
                x = dense_t(ACTIVATION(x), layer["kernel"], kt)
            x = x + layer["bias"]
        return jax.vmap(self._draw)(x, keys)

    def _draw(self, logits: jax.Array, key: jax.Array) -> jax.Array:
        d = self._dist
        return d.postprocess(d.sample_no_postprocessing(logits, key))

    def sample(self, params: dict, obs: jax.Array, key: jax.Array) -> jax.Array:
        """Reparameterized tanh-Gaussian sample (differentiable in params and obs)."""
        return self._draw(self.logits(params, obs), key)

    def mode(self, params: dict, obs: jax.Array) -> jax.Array:
        return self._dist.mode(self.logits(params, obs))

    def act(self, params: dict, obs: jax.Array, key: jax.Array, deterministic: bool):
        """bench.api.Policy 'jax' signature."""
        return self.mode(params, obs) if deterministic else self.sample(params, obs, key)


def bc_pairs(task, demo) -> tuple[jax.Array, jax.Array]:
    """The demo's BC pairs flattened over demos: observations o_0..o_{T-1} (N, obs_size)
    with the actions a_0..a_{T-1} (N, action_size) taken in them."""
    return (jnp.asarray(demo.obs[:, :-1]).reshape(-1, task.obs_size),
            jnp.asarray(demo.actions).reshape(-1, task.action_size))


def bc_loss(policy: TanhGaussianPolicy, params: dict, obs: jax.Array, actions: jax.Array,
            key: jax.Array, samples: int) -> jax.Array:
    """The original BC warm start: squared error of reparameterized samples to the demo
    actions, summed over action dims, averaged over samples and demo steps.
    obs (N, obs_dim) pairs with actions (N, act_dim): o_t with a_t (state BEFORE action)."""
    keys = jax.random.split(key, samples)
    a = jax.vmap(lambda k: jax.vmap(policy.sample, in_axes=(None, 0, 0))(
        params, obs, jax.random.split(k, obs.shape[0])))(keys)
    return jnp.mean(jnp.sum((a - actions[None]) ** 2, axis=-1))


def bc_optimizer(learning_rate: float, max_grad_norm: float):
    """The original BC bootstrap's optimizer: global-norm clip, then Adam."""
    return optax.chain(optax.clip_by_global_norm(max_grad_norm), optax.adam(learning_rate))


def make_bc_step(policy: TanhGaussianPolicy, opt, obs: jax.Array, actions: jax.Array,
                 samples: int):
    """step(params, opt_state, key) -> (params, opt_state, loss, grad_norm): one BC update."""

    def step(params, opt_state, key):
        loss, g = jax.value_and_grad(
            lambda p: bc_loss(policy, p, obs, actions, key, samples))(params)
        upd, opt_state = opt.update(g, opt_state, params)
        return optax.apply_updates(params, upd), opt_state, loss, optax.global_norm(g)

    return step
