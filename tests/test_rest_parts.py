"""results/substep/scripts/rest_parts.py (session 59) asks what the update has that its parts
lack. Checked: its policy without the observations' gradient samples the same actions with
the same gradient in the parameters and none in the observations, and its summary's medians
and ratios on hand-made numbers."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest


@pytest.fixture(scope="module")
def rest_parts(substep_script):
    with substep_script("rest_parts") as mod:
        yield mod


def test_obs_cut_samples_the_same_with_no_gradient_into_the_observations(rest_parts):
    from methods.common.policy import ObsNorm, TanhGaussianPolicy
    policy = TanhGaussianPolicy(5, 2, (16, 8))
    params = policy.init(jax.random.PRNGKey(0), ObsNorm(jnp.zeros(5), jnp.ones(5)))
    obs = jax.random.normal(jax.random.PRNGKey(1), (4, 5))
    keys = jax.random.split(jax.random.PRNGKey(2), 4)
    kt = policy.kernels_t(params)
    cut = rest_parts.ObsCut(policy)
    assert cut.kernels_t is not None and cut.action_size == 2  # the rest is the policy's

    def value(pol, p, o):
        return jnp.sum(pol.sample_batch(p, o, keys, kt) ** 2)

    for f in (value,
              lambda pol, p, o: jnp.sum(jax.vmap(pol.sample, (None, 0, 0))(p, o, keys) ** 2)):
        v, (gp, go) = jax.value_and_grad(f, argnums=(1, 2))(policy, params, obs)
        vc, (gpc, goc) = jax.value_and_grad(f, argnums=(1, 2))(cut, params, obs)
        assert float(vc) == float(v)
        assert float(jnp.max(jnp.abs(go))) > 0 and float(jnp.max(jnp.abs(goc))) == 0.0
        for a, b in zip(jax.tree.leaves(gp), jax.tree.leaves(gpc)):
            np.testing.assert_array_equal(a, b)


def test_summary_takes_medians_and_ratios_per_round(rest_parts):
    seconds = {"forward": [1.0, 2.0, 1.0], "update": [3.0, 8.0, 4.0],
               "grad": [3.0, 6.0, 3.0]}
    lines = rest_parts.summary_lines(seconds, {"grad": 20.0, "policy_grad": 12.4,
                                               "physics_grad": 6.0}, "t, B = 4")
    assert lines[0].startswith("t, B = 4; median s per call")
    # update / forward per round 3, 4, 4; / update 1, 1, 1
    assert lines[2] == ("  update            4.0000  4.000x (3.000-4.000x)  "
                        "1.000x (1.000-1.000x)")
    # grad / forward 3, 3, 3; / update 1, 0.75, 0.75
    assert lines[3] == ("  grad              3.0000  3.000x (3.000-3.000x)  "
                        "0.750x (0.750-1.000x)")
    assert lines[4] == ("  working memory, MiB: grad 20, policy_grad 12, physics_grad 6 "
                        "(the parts' sum 18)")
