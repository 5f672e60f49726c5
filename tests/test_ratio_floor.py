"""results/substep/scripts/ratio_floor.py (session 57) times the parts of ILD's update, each
against its own forward. Checked: its programs compute what they claim (the gradient
programs' values are the forward programs' values; their gradients are the directional
derivatives a central difference measures), and its summary's medians and ratios on
hand-made rows."""
import dataclasses

import jax
import jax.numpy as jnp
import pytest


@pytest.fixture(scope="module")
def ratio_floor(substep_script):
    with substep_script("ratio_floor") as mod:
        yield mod


def _directional(f, x, d, eps):
    return (f(x + eps * d) - f(x - eps * d)) / (2 * eps)


def test_parts_compute_their_values_and_gradients(ratio_floor):
    from methods.ild.benchmark import speed_setup, task_config
    from methods.ild.config import ILDConfig
    from tasks import make_task
    task = make_task("pointmass")
    cfg = task_config("pointmass", 4)
    setup = speed_setup(task, ILDConfig(num_envs=4))
    (pol_f, (params, obs)), (pol_g, _) = ratio_floor.policy_programs(task, cfg, setup)
    value, (g_params, g_obs) = pol_g(params, obs)
    assert value == pytest.approx(float(pol_f(params, obs)), rel=1e-5)
    d = jax.random.normal(jax.random.PRNGKey(1), obs.shape)
    fd = _directional(lambda o: pol_f(params, o), obs, d, 1e-2)
    assert float(jnp.sum(g_obs * d)) == pytest.approx(float(fd), rel=2e-2)
    kernel = params["net"]["params"]["hidden_1"]["kernel"]
    dk = jax.random.normal(jax.random.PRNGKey(2), kernel.shape)

    def with_kernel(k):
        p = jax.tree.map(lambda x: x, params)
        p["net"]["params"]["hidden_1"]["kernel"] = k
        return pol_f(p, obs)
    fd = _directional(with_kernel, kernel, dk, 1e-2)
    got = float(jnp.sum(g_params["net"]["params"]["hidden_1"]["kernel"] * dk))
    assert got == pytest.approx(float(fd), rel=2e-2)

    (brax_f, (acts,)), (train_f, _), (grad, _) = ratio_floor.physics_programs(task, cfg, setup)
    value, g_acts = grad(acts)
    assert value == pytest.approx(float(brax_f(acts)), rel=1e-5)
    assert value == pytest.approx(float(train_f(acts)), rel=1e-5)
    assert float(jnp.max(jnp.abs(g_acts))) > 0
    # Central differences of the physics alone: the per-step gradient normalization and the
    # truncation make the gradient a different vector, so compare it without them.
    raw = dataclasses.replace(cfg, grad_normalization=False,
                              truncation=task.episode_length)
    (_, _), (raw_f, _), (raw_g, _) = ratio_floor.physics_programs(task, raw, setup)
    d = jax.random.normal(jax.random.PRNGKey(3), acts.shape) * 0.1
    fd = _directional(raw_f, acts, d, 3e-3)  # float32: 0.4% from the gradient at this step
    assert float(jnp.sum(raw_g(acts)[1] * d)) == pytest.approx(float(fd), rel=3e-2)

    (loss_f, (x,)), (loss_g, _) = ratio_floor.loss_programs(task, cfg, setup)
    value, g_x = loss_g(x)
    assert value == pytest.approx(float(loss_f(x)), rel=1e-6)
    d = jax.random.normal(jax.random.PRNGKey(4), x.shape)
    # A small step: pointmass's 2-D states switch nearest neighbours at 1e-3 (Chamfer's min)
    fd = _directional(loss_f, x, d, 1e-4)
    assert float(jnp.sum(g_x * d)) == pytest.approx(float(fd), rel=2e-2)


def test_summary_takes_medians_and_each_parts_ratio(ratio_floor):
    seconds = {"forward": [1.0, 2.0, 1.0], "update": [3.0, 7.0, 3.5],
               "policy_fwd": [0.2, 0.3, 0.25], "policy_grad": [0.7, 0.9, 0.8],
               "physics_fwd": [0.7, 1.5, 0.6], "physics_train_fwd": [0.6, 1.2, 0.5],
               "physics_grad": [2.0, 3.6, 1.5], "loss_fwd": [0.05, 0.1, 0.05],
               "loss_grad": [0.05, 0.1, 0.06]}
    rows = [{"task": "t", "batch": 4, "part": p, "round": r, "seconds": s}
            for p, ss in seconds.items() for r, s in enumerate(ss)]
    lines = ratio_floor.summary_lines(rows)
    assert lines[0] == "t, B = 4, 3 rounds; medians, s per call:"
    assert "forward 1.0000, update 3.5000" in lines[1]
    assert lines[2] == "  update / forward 3.50x (3.00-3.50x)"  # 3/1, 7/2, 3.5/1
    assert lines[3] == "  policy: grad / fwd 3.20x (3.00-3.50x)"  # 3.5, 3, 3.2
    # physics grad / train fwd: 3.33, 3.0, 3.0; grad / brax fwd: 2.86, 2.4, 2.5;
    # train / brax: 0.857, 0.8, 0.833
    assert lines[4] == ("  physics: grad / train fwd 3.00x (3.00-3.33x), grad / brax fwd "
                        "2.50x (2.40-2.86x), train fwd / brax fwd 0.83x (0.80-0.86x)")
    assert lines[5] == "  loss: grad / fwd 1.00x (1.00-1.20x)"  # 1, 1, 1.2
    # medians: policy 0.25 + physics 0.7 + loss 0.05 = 1.0 of the forward's 1.0
    assert lines[6] == ("  forward's parts: policy_fwd + physics_fwd + loss_fwd = 1.0000 s of "
                        "1.0000 (policy 25%, physics 70%, loss 5%); the rest 0.0000 s")
    # the update's: 0.8 + 2.0 + 0.06 = 2.86 of 3.5 (82%), the rest 0.64
    assert lines[7].startswith("  update's parts: policy_grad + physics_grad + loss_grad = "
                               "2.8600 s of 3.5000 (82%)")
    assert lines[7].endswith(" 0.6400 s")
    # over 3x: policy 0.8 - 0.75, physics 2.0 - 2.1, loss 0.06 - 0.15, rest 0.64 - 0
    assert lines[8].endswith("policy +0.0500, physics -0.1000, loss -0.0900, rest +0.6400; "
                             "3x the forward 3.0000, the update 3.5000")
