"""Transfer evaluation: zero perturbation == nominal exactly; each family changes what it
claims; noise is reproducible; normalization uses references under the same perturbation."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.evaluator import EvalConfig, Evaluator
from bench.perturb import FAMILIES, Perturbation, perturbed_task
from bench import transfer as tr
from tasks import make_task
from tasks.demo import load_demo
from bench.expert import expert_policy

CFG = EvalConfig(num_episodes=8)


@pytest.fixture(scope="module")
def pm():
    task = make_task("pointmass")
    return task, load_demo(task.spec.demo_path, task), expert_policy("pointmass")


@pytest.mark.parametrize("family", FAMILIES)
def test_zero_magnitude_is_exactly_nominal(family, pm, monkeypatch, tmp_path):
    task, demo, pol = pm
    monkeypatch.setattr(tr, "REF_DIR", str(tmp_path))
    nominal = Evaluator(task, CFG, demo.expert_return, demo.random_return).evaluate(pol, 3)
    out = tr.evaluate_transfer(task, demo, pol, 3, CFG, [Perturbation(family, 0.0)])
    (entry,) = out.values()
    assert entry["return"] == nominal.mean_return
    assert entry["normalized"] == nominal.mean_normalized


def _rollout(task, actions, key=jax.random.PRNGKey(0)):
    env = task.env
    s = env.reset(key)
    s, obs = jax.lax.scan(lambda s, a: (env.step(s, a), (s.obs, s.pipeline_state)), s,
                          actions)
    return obs


@pytest.mark.parametrize("family,magnitude", [("mass", 1.0), ("actuator", -0.5),
                                              ("action_noise", 0.3), ("action_bias", 0.3),
                                              ("init_noise", 0.2)])
def test_each_family_changes_the_trajectory_of_fixed_actions(family, magnitude, pm):
    task = pm[0]
    actions = 0.5 * jnp.ones((20, 1))
    _, base = _rollout(perturbed_task(task, Perturbation(family, 0.0)), actions)
    _, pert = _rollout(perturbed_task(task, Perturbation(family, magnitude)), actions)
    assert not np.allclose(base, pert)


def test_mass_doubles_inertia_by_hand(pm):
    """Pointmass: v_1 = v_0 + dt * f / m, so doubling m halves the velocity change."""
    task = pm[0]
    obs_b, ps_b = _rollout(perturbed_task(task, Perturbation("mass", 0.0)), jnp.ones((2, 1)))
    obs_m, ps_m = _rollout(perturbed_task(task, Perturbation("mass", 1.0)), jnp.ones((2, 1)))
    dv_base = ps_b[1, 1] - ps_b[0, 1]
    dv_mass = ps_m[1, 1] - ps_m[0, 1]
    np.testing.assert_allclose(dv_mass, dv_base / 2, rtol=1e-5)


def test_friction_leaves_a_contact_free_task_alone(pm):
    task = pm[0]
    a = 0.5 * jnp.ones((10, 1))
    np.testing.assert_array_equal(_rollout(perturbed_task(task, Perturbation("friction", -0.5)),
                                           a)[1], _rollout(task, a)[1])


def test_obs_noise_changes_what_the_policy_sees_not_the_physics(pm):
    task = pm[0]
    a = 0.5 * jnp.ones((10, 1))
    obs, ps = _rollout(perturbed_task(task, Perturbation("obs_noise", 0.1)), a)
    obs0, ps0 = _rollout(task, a)
    np.testing.assert_array_equal(ps, ps0)
    assert not np.allclose(obs[1:], obs0[1:])


def test_noise_with_a_fixed_key_is_reproducible(pm):
    task, demo, pol = pm
    ev = Evaluator(perturbed_task(task, Perturbation("action_noise", 0.3)), CFG)
    a, b = ev.evaluate(pol, 5).returns, ev.evaluate(pol, 5).returns
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, ev.evaluate(pol, 6).returns)


def test_traced_magnitudes_at_zero_reproduce_the_nominal_episodes(pm):
    """The one-compilation path (magnitudes as a traced argument) with every magnitude 0
    scores like the nominal env up to float32 rounding (another compiled program: ~1e-7
    relative); magnitude 0 itself is routed to the nominal task, so it is exact."""
    from bench.perturb import FAMILIES as F, _Perturbed
    task, demo, pol = pm
    zero = task.__class__(spec=task.spec, env=_Perturbed(task.env, np.zeros(len(F), np.float32)))
    a = Evaluator(task, CFG).evaluate(pol, 4)
    b = Evaluator(zero, CFG).evaluate(pol, 4)
    np.testing.assert_allclose(a.returns, b.returns, rtol=1e-6)
    np.testing.assert_allclose(a.trajectory, b.trajectory, rtol=1e-6, atol=1e-6)
    assert perturbed_task(task, Perturbation("mass", 0.0)) is task


def test_one_compilation_serves_every_perturbation(pm):
    from bench.api import Policy
    from bench.evaluator import _jax_episodes
    task, demo, expert = pm
    # a policy of its own: the expert's compiled episodes are shared with every test of the
    # process that scores it (transfer references at other episode counts)
    pol = Policy(lambda params, obs, key, det: expert.act(params, obs, key, det), expert.params)
    ps = [Perturbation("mass", 0.7), Perturbation("actuator", -0.4),
          Perturbation("action_noise", 0.2), Perturbation("init_noise", 0.1)]
    rets = [Evaluator(perturbed_task(task, p), CFG).evaluate(pol, 2).mean_return for p in ps]
    assert len(set(rets)) == len(ps)  # each perturbation scored differently ...
    template = perturbed_task(task, ps[0]).env.template
    f = _jax_episodes(template, pol.act, pol.kind, task.episode_length, True, pol.init_memory)
    assert f._cache_size() == 1  # ... by one compiled program


@pytest.mark.parametrize("family,magnitude", [("action_noise", 0.3), ("mass", 0.5),
                                              ("obs_noise", 0.1), ("action_bias", 0.3)])
def test_host_and_jax_policies_agree_under_perturbation(family, magnitude, pm):
    """The host path (torch/numpy policies: one batched env call per step) passes the same
    magnitudes as the jitted-episode path."""
    from bench.api import Policy
    task = pm[0]
    ev = Evaluator(perturbed_task(task, Perturbation(family, magnitude)), CFG)

    def jax_pd(params, obs, key, deterministic):
        return jnp.clip(-params * obs[..., :1] - obs[..., 1:], -1, 1)

    def host_pd(params, obs, rng, deterministic):
        return np.clip(-params * obs[:, :1] - obs[:, 1:], -1, 1)

    a = ev.evaluate(Policy(jax_pd, 2.0), seed=1).returns
    b = ev.evaluate(Policy(host_pd, 2.0, kind="host"), seed=1).returns
    np.testing.assert_allclose(a, b, rtol=1e-5)
    nominal = Evaluator(task, CFG).evaluate(Policy(jax_pd, 2.0), seed=1).returns
    assert not np.allclose(a, nominal)


def test_normalization_uses_references_under_the_same_perturbation(pm, monkeypatch,
                                                                   tmp_path):
    task, demo, pol = pm
    monkeypatch.setattr(tr, "REF_DIR", str(tmp_path))
    p = Perturbation("actuator", -0.5)
    (entry,) = tr.evaluate_transfer(task, demo, pol, 0, CFG, [p]).values()
    r_exp, r_rand = entry["expert_return"], entry["random_return"]
    assert r_exp != demo.expert_return  # measured under the perturbation, not nominal
    ev = Evaluator(perturbed_task(task, p), EvalConfig(num_episodes=128))
    assert r_exp == ev.evaluate(pol, 0).mean_return
    assert entry["normalized"] == pytest.approx((entry["return"] - r_rand) / (r_exp - r_rand))
    assert (tmp_path / "pointmass.json").exists()  # cached for the next run


@pytest.mark.parametrize("kw,match", [(("gravity", 1.0), "unknown perturbation family"),
                                      (("mass", -1.0), "must be > -1"),
                                      (("action_noise", -0.1), "must be >= 0")])
def test_invalid_perturbations(kw, match):
    with pytest.raises(ValueError, match=match):
        Perturbation(*kw)


@pytest.mark.parametrize("task_name,family,expect", [
    ("pointmass", "friction", "no contacts"), ("inverted_pendulum", "friction", "no geom pair"),
    ("hopper", "mass", "spring_mass_scale = 1"), ("hopper", "friction", None),
    ("inverted_pendulum", "mass", None), ("pointmass", "mass", None)])
def test_families_that_cannot_change_a_task_are_flagged(task_name, family, expect):
    from bench.calibrate import _undeclared
    from bench.perturb import inapplicable
    task = make_task(task_name)  # what the family could change, before any declaration:
    task = task.__class__(spec=_undeclared(task.spec), env=task.env)
    why = inapplicable(task, Perturbation(family, 0.3))
    assert (why is None) if expect is None else (expect in why)


def test_skipped_families_are_recorded_and_left_out_of_the_summary(pm, monkeypatch, tmp_path):
    task, demo, pol = pm
    monkeypatch.setattr(tr, "REF_DIR", str(tmp_path))
    out = tr.evaluate_transfer(task, demo, pol, 0, CFG, [Perturbation("friction", -0.5),
                                                         Perturbation("mass", 0.3)])
    assert "no contacts" in out["friction=-0.5"]["skipped"]
    assert tr.transfer_summary(out) == out["mass=0.3"]["normalized"]


# -- per-task defaults (bench/calibrate.py) -------------------------------------------------

@pytest.mark.parametrize("points,expect,why", [
    # kept = (e - 0) / 100, gap = (e - r) / 100
    ([(0.1, 95, 0), (0.2, 85, 10), (0.3, 70, 0)], 0.2, "0.3 fails"),      # kept 0.70 < 0.8
    ([(0.1, 95, 0), (0.2, 85, 50), (0.3, 90, 0)], 0.1, "0.2 fails"),      # gap 0.35 < 0.5
    ([(0.1, 95, 0), (0.2, 90, 5)], 0.2, "up to the generic default"),
    ([(0.1, 60, 0), (0.2, 90, 0)], None, "keeps 0.60"),                    # smallest fails
    ([(0.1, 100, 0), (0.2, 100, 0)], None, "no measured effect"),
])
def test_calibration_choice_by_hand(points, expect, why):
    from bench.calibrate import choose
    default, reason = choose((100.0, 0.0), points)
    assert default == expect and why in reason


def test_calibration_is_sign_agnostic_and_catches_expert_worse_than_random():
    """Reacher-like negative returns: observation noise that makes the expert worse than
    random (what reacher's obs_noise 0.05 did) must not be chosen."""
    from bench.calibrate import choose
    default, _ = choose((-18.0, -106.0), [(0.005, -20.0, -106.0), (0.01, -40.0, -106.0),
                                          (0.05, -169.0, -106.0)])
    assert default == 0.005  # kept 0.98, then (-40 + 106) / 88 = 0.75 < 0.8
    with pytest.raises(ValueError, match="retrain the expert"):
        choose((-110.0, -106.0), [(0.1, -20.0, -106.0)])


def test_calibrate_pointmass_end_to_end(monkeypatch, tmp_path):
    from bench import calibrate as cal
    monkeypatch.setattr(tr, "REF_DIR", str(tmp_path / "refs"))
    monkeypatch.setattr(cal, "CAL_DIR", str(tmp_path / "cal"))
    out = cal.calibrate("pointmass", log=lambda *a: None)
    assert "no contacts" in out["families"]["friction"]["reason"]
    e0, r0 = out["nominal"]["expert"], out["nominal"]["random"]
    for fam, default in out["transfer"]:
        pts = out["families"][fam]["points"]
        ok = [p for p in pts if abs(p["magnitude"]) <= abs(default)]
        assert ok and all((p["expert"] - r0) / (e0 - r0) >= cal.KEEP for p in ok)
    assert (tmp_path / "cal" / "pointmass.md").read_text().count("**default**") == \
        len(out["transfer"])


def test_registry_defaults_are_the_committed_calibration():
    """A task's TaskSpec.transfer is data copied from its calibration; they must agree."""
    from bench.calibrate import load
    from tasks.registry import TASKS
    checked = 0
    for name, spec in TASKS.items():
        cal = load(name)
        if cal is None:
            continue
        assert spec.transfer == tuple((f, m) for f, m in cal["transfer"]), name
        checked += 1
    assert checked >= 3  # inverted_pendulum, reacher, hopper


def test_default_summary_refuses_records_scored_under_other_defaults():
    task = make_task("hopper")
    entry = {"normalized": 0.5, "family": None, "magnitude": None}
    full = {p.key: dict(entry, family=p.family, magnitude=p.magnitude)
            for p in tr.default_set(task)}
    assert tr.default_summary(full, task) == pytest.approx(0.5)
    stale = dict(full)
    stale.pop(next(iter(stale)))
    stale["init_noise=0.123"] = dict(entry, family="init_noise", magnitude=0.123)
    assert tr.default_summary(stale, task) is None


def test_dynamics_effect_is_zero_at_zero_and_large_for_a_real_change(pm):
    from bench.calibrate import EFFECT_TOL, dynamics_effect
    task = pm[0]
    assert dynamics_effect(task, Perturbation("mass", 0.0)) == 0.0
    assert dynamics_effect(task, Perturbation("mass", 0.3)) > 10 * EFFECT_TOL


def test_references_fall_back_to_the_user_cache_where_the_package_folder_is_read_only(
        tmp_path, monkeypatch):
    """An installed wheel's reference folder may be read-only: a new entry then goes to the
    user's cache and is read back on top of the packaged ones; the packaged file is
    untouched. Where the folder is writable, entries are stored beside the packaged ones.
    (Read-only is simulated: file modes do not bind root.)"""
    import os
    import bench.transfer as tr
    pkg, user = tmp_path / "pkg", tmp_path / "user"
    pkg.mkdir()
    (pkg / "hopper.json").write_text('{"sha": {"mass:0.3": {"expert": 1.0, "random": 0.0}}}')
    monkeypatch.setattr(tr, "REF_DIR", str(pkg))
    monkeypatch.setattr(tr, "USER_REF_DIR", str(user))
    real_write, real_access = tr.write_json_atomic, os.access
    read_only = [True]

    def write(path, obj):
        if read_only[0] and path.startswith(str(pkg)):
            raise PermissionError(13, "Permission denied", path)
        return real_write(path, obj)
    monkeypatch.setattr(tr, "write_json_atomic", write)
    monkeypatch.setattr(os, "access", lambda p, mode, **k: False if read_only[0] and
                        str(p).startswith(str(pkg)) else real_access(p, mode, **k))
    path = tr.store_reference("hopper.json", "sha", {"expert": 2.0, "random": 0.5},
                              subkey="friction:-0.5")
    assert path == str(user / "hopper.json")
    assert tr.load_references("hopper.json")["sha"] == {
        "mass:0.3": {"expert": 1.0, "random": 0.0}, "friction:-0.5": {"expert": 2.0, "random": 0.5}}
    assert "friction" not in (pkg / "hopper.json").read_text()
    read_only[0] = False  # a writable package folder (a checkout): stored there, cache unread
    assert tr.store_reference("hopper.json", "sha2", {"expert": 3.0, "random": 1.0},
                              subkey="mass:0.3") == str(pkg / "hopper.json")
    assert "friction:-0.5" not in tr.load_references("hopper.json")["sha"]
