"""Training in changed dynamics (`--train-dynamics`): parsing and its errors, the env a
method is handed (physics scaled in before the plan, noise wrapped around it), fixed and
fresh noise, and the run's record (scored under the changed dynamics, nominal beside it)."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench import transfer as tr
from bench.api import MethodSpec, Policy, TrainResult, Uses
from bench.budget import Budget
from bench.cli import main
from bench.evaluator import EvalConfig, Evaluator
from bench.perturb import DEFAULTS, Perturbation, parse_dynamics, perturbed_task
from bench.access import TaskView
from bench.runner import RunRequest, execute, prepare
from tasks import make_task

CFG = EvalConfig(num_episodes=8)


@pytest.mark.parametrize("text,task,expect", [
    ("action_bias:0.2:fixed", "pointmass", Perturbation("action_bias", 0.2, "fixed")),
    ("action_noise:0.5", "pointmass", Perturbation("action_noise", 0.5, "fresh")),
    ("action_noise:fresh", None, Perturbation("action_noise", DEFAULTS["action_noise"])),
    ("mass", None, Perturbation("mass", DEFAULTS["mass"])),
    # the task's own default magnitude (TaskSpec.transfer): hopper's action bias is 0.1
    ("action_bias", "hopper", Perturbation("action_bias", 0.1)),
    # a family the task's transfer column leaves out still trains (it changes the physics)
    ("init_noise:0.05", "hopper", Perturbation("init_noise", 0.05)),
    ("test_noise:fixed", "cloth", Perturbation("test_noise", 1.0, "fixed")),
])
def test_parse_dynamics(text, task, expect):
    p = parse_dynamics(text, None if task is None else make_task(task))
    assert p == expect
    assert p.key == f"{expect.family}={expect.magnitude:g}" + (
        ":fixed" if expect.noise == "fixed" else "")


@pytest.mark.parametrize("text,task,match", [
    ("gravity:1", None, "unknown family 'gravity'; families: init_noise, action_noise"),
    ("mass:0.3:fixed", None, "mass draws no noise, so it has no fixed mode"),
    ("action_noise:9", None, "action_noise magnitude must be in [0, 2]"),
    ("action_noise:0", None, "0 is the nominal dynamics"),
    ("mass:-0.95", None, "mass magnitude must be in [-0.9, 3]"),
    ("action_noise:lots", None, "magnitude 'lots' is not a number"),
    ("action_noise:0.1:0.2", None, "expected FAMILY[:MAGNITUDE][:fixed|fresh]"),
    ("friction:0.5", "pointmass", "friction cannot change the dynamics of task 'pointmass': "
                                  "the task has no contacts; families for this task: "
                                  "init_noise, action_noise, action_bias, obs_noise, actuator, "
                                  "mass"),
    ("test_noise", "hopper", "task 'hopper' declares no test_noise dynamics"),
    ("mass:0.3", "cloth", "task 'cloth' has no physical parameters that mass scales"),
    ("mass:0.3", "hopper", "spring_mass_scale = 1"),
])
def test_parse_dynamics_refuses_bad_input(text, task, match):
    with pytest.raises(ValueError, match=match.replace("[", r"\[").replace("]", r"\]")):
        parse_dynamics(text, None if task is None else make_task(task))


def test_bad_training_dynamics_exit_2_and_write_nothing(capsys, tmp_path):
    store = tmp_path / "runs"
    code = main(["run", "--method", "bc", "--task", "pointmass", "--budget", "5s",
                 "--train-dynamics", "friction:0.5", "--store", str(store)])
    assert code == 2
    assert "families for this task: init_noise" in capsys.readouterr().err
    assert not store.exists()


def _view(task_name, dynamics, uses=Uses(), plan=None):
    return TaskView(make_task(task_name), uses, "probe", plan, dynamics)


def test_physical_families_are_scaled_into_the_training_env_by_hand():
    """Pointmass: v' = v + dt * force_scale * (1 + m_act) * a / (mass * (1 + m_mass)), with
    dt 0.05, force_scale 2 and mass 1. The registry's task keeps its parameters."""
    a = jnp.array([0.5])
    for p, dv in [(Perturbation("mass", 1.0), 0.05 * 2 * 0.5 / 2.0),
                  (Perturbation("actuator", -0.5), 0.05 * 1.0 * 0.5 / 1.0)]:
        env = _view("pointmass", p).env
        s = env.reset(jax.random.PRNGKey(0))
        s2 = env.step(s, a)
        assert float(s2.obs[1] - s.obs[1]) == pytest.approx(dv, rel=1e-5)
    inner = make_task("pointmass").env.unwrapped
    assert (inner.mass, inner.force_scale) == (1.0, 2.0)


def test_fixed_noise_is_one_bias_for_every_episode_in_training_and_scoring():
    """action_bias 0.5, fixed: every reset key gives the same bias, the one the evaluator's
    env of the same dynamics draws; fresh: each reset key its own. By hand on pointmass from
    rest at the origin with action 0: v' = dt * force_scale * clip(bias) = 0.1 * bias."""
    fixed, fresh = Perturbation("action_bias", 0.5, "fixed"), Perturbation("action_bias", 0.5)
    k1, k2 = jax.random.PRNGKey(1), jax.random.PRNGKey(2)
    train = _view("pointmass", fixed).env
    scored = perturbed_task(make_task("pointmass"), fixed).env
    b1, b2 = (train.reset(k).info["perturb_bias"] for k in (k1, k2))
    np.testing.assert_array_equal(b1, b2)
    np.testing.assert_array_equal(b1, scored.reset(k1).info["perturb_bias"])
    assert 0 < abs(float(b1[0])) <= 0.5
    s = train.reset(k1)
    s = s.replace(pipeline_state=jnp.zeros(2), obs=jnp.zeros(2))
    assert float(train.step(s, jnp.zeros(1)).obs[1]) == pytest.approx(0.1 * float(b1[0]),
                                                                       rel=1e-5)
    fr = _view("pointmass", fresh).env
    assert not np.array_equal(fr.reset(k1).info["perturb_bias"],
                              fr.reset(k2).info["perturb_bias"])


def test_fixed_action_noise_repeats_its_sequence_across_episodes():
    p = Perturbation("action_noise", 0.3, "fixed")
    env = _view("pointmass", p).env

    def velocities(key):
        s = env.reset(key).replace(pipeline_state=jnp.zeros(2), obs=jnp.zeros(2))
        out = []
        for _ in range(3):
            s = env.step(s, jnp.zeros(1))
            out.append(float(s.obs[1]))
        return out
    a, b = velocities(jax.random.PRNGKey(1)), velocities(jax.random.PRNGKey(7))
    assert a == b and len(set(np.diff([0.0] + a))) == 3  # one sequence, not a constant


def test_a_plan_is_built_on_the_scaled_parameters():
    """The plan's rewrites copy the scene's parameters when they are built: the training
    env of mass +50% on inverted_pendulum carries masses and inertias x1.5 under its CPU
    plan, the registry's task its own."""
    from tasks.physics.plan import plan_for
    nominal = make_task("inverted_pendulum").env.unwrapped.sys
    planned = _view("inverted_pendulum", Perturbation("mass", 0.5), Uses(sim_gradients=True),
                    plan_for("inverted_pendulum", "cpu")).env.unwrapped
    assert "pipeline_step" in vars(planned)  # the plan's rebuilt substep loop
    np.testing.assert_allclose(planned.sys.link.inertia.mass, 1.5 * nominal.link.inertia.mass)
    np.testing.assert_allclose(planned.sys.link.inertia.i, 1.5 * nominal.link.inertia.i)
    np.testing.assert_allclose(planned.sys.body_mass, 1.5 * nominal.body_mass)


@pytest.mark.slow
def test_a_plan_steps_the_scaled_physics():
    """inverted_pendulum's CPU plan (positional joints, lean substeps, planar adjoint) reads
    the scene's masses once, when it is built: the training env scales them in before the
    plan, so its step and gradient are those of the evaluator's (traced) changed physics."""
    from tasks.physics.plan import plan_for
    p = Perturbation("mass", 0.5)
    task = make_task("inverted_pendulum")
    planned = _view("inverted_pendulum", p, Uses(sim_gradients=True),
                    plan_for("inverted_pendulum", "cpu")).env
    reference = perturbed_task(task, p).env

    def final_q(env):
        def f(a):
            s = env.reset(jax.random.PRNGKey(3))
            for _ in range(2):
                s = env.step(s, a)
            return s.pipeline_state.q[1], s.pipeline_state.q
        return jax.jit(jax.value_and_grad(f, has_aux=True))(jnp.array([0.7]))

    (_, q_plan), g_plan = final_q(planned)
    (_, q_ref), g_ref = final_q(reference)
    (_, q_nominal), _ = final_q(task.env)
    np.testing.assert_allclose(q_plan, q_ref, rtol=1e-5, atol=1e-6)
    assert np.max(np.abs(np.asarray(q_ref) - np.asarray(q_nominal))) > 1e-3
    np.testing.assert_allclose(g_plan, g_ref, rtol=1e-4)


def test_cloth_fixed_test_noise_is_the_same_for_every_episode():
    p = Perturbation("test_noise", 1.0, "fixed")
    env = _view("cloth", p).env
    i1, i2 = (env.reset(jax.random.PRNGKey(k)).info for k in (1, 2))
    np.testing.assert_array_equal(i1["bias"], i2["bias"])
    np.testing.assert_array_equal(i1["noise_key"], i2["noise_key"])
    assert float(jnp.max(jnp.abs(i1["bias"]))) > 0
    fresh = _view("cloth", Perturbation("test_noise", 1.0)).env
    assert not np.array_equal(fresh.reset(jax.random.PRNGKey(1)).info["bias"],
                              fresh.reset(jax.random.PRNGKey(2)).info["bias"])


def _probe_train(task, demo, config, ctx, seed):
    """Steps the env it was handed once from rest with action 0 and reports the velocity
    (pointmass: dt * force_scale * bias), then returns a PD policy."""
    s = task.env.reset(jax.random.PRNGKey(0))
    s = s.replace(pipeline_state=jnp.zeros(2), obs=jnp.zeros(2))
    v = float(task.env.step(s, jnp.zeros(1)).obs[1])
    pol = Policy(lambda g, o, k, d: jnp.clip(-g * o[..., :1] - o[..., 1:], -1, 1),
                 jnp.asarray(3.0))
    ctx.report(pol, 100, {"probe/v": v})
    return TrainResult(pol, env_steps=100)


@pytest.fixture
def probe(temp_method):
    @dataclasses.dataclass(frozen=True)
    class ProbeConfig:
        pass
    return temp_method(MethodSpec(name="probe", train=_probe_train, config_cls=ProbeConfig,
                                  uses=Uses()))


def _request(dynamics=None):
    return RunRequest(method="probe", task="pointmass", seed=0,
                      budget=Budget(env_steps=100, evals=1), eval=CFG,
                      train_dynamics=dynamics)


def test_a_run_trains_and_is_scored_in_the_changed_dynamics(probe, store, monkeypatch,
                                                             tmp_path):
    monkeypatch.setattr(tr, "REF_DIR", str(tmp_path / "refs"))
    nominal_p, changed_p = prepare(_request()), prepare(_request("action_bias:0.5:fixed"))
    assert changed_p.run_id != nominal_p.run_id
    assert changed_p.run_id == prepare(_request("action_bias:0.5:fixed")).run_id
    assert prepare(_request("action_bias:0.5")).run_id != changed_p.run_id  # fresh != fixed
    rec, _ = execute(changed_p, store, log=lambda s: None)
    assert rec["status"] == "ok"
    assert rec["train_dynamics"] == {"family": "action_bias", "magnitude": 0.5,
                                     "noise": "fixed", "key": "action_bias=0.5:fixed"}
    p = Perturbation("action_bias", 0.5, "fixed")
    task = make_task("pointmass")
    bias = perturbed_task(task, p).env.reset(jax.random.PRNGKey(0)).info["perturb_bias"]
    assert rec["train_metrics"]["probe/v"] == pytest.approx(0.1 * float(bias[0]), rel=1e-5)
    # headline: scored under the changed dynamics against references measured under them
    r_exp, r_rand = tr.references(task, changed_p.demo, p)
    assert rec["references"] == {"expert_return": r_exp, "random_return": r_rand}
    assert r_exp != changed_p.demo.expert_return
    pol = Policy(lambda g, o, k, d: jnp.clip(-g * o[..., :1] - o[..., 1:], -1, 1),
                 jnp.asarray(3.0))
    changed = Evaluator(perturbed_task(task, p), CFG, r_exp, r_rand).evaluate(pol, 0)
    assert rec["final_return"] == pytest.approx(changed.mean_return, rel=1e-6)
    nominal = Evaluator(task, CFG, changed_p.demo.expert_return,
                        changed_p.demo.random_return).evaluate(pol, 0)
    assert rec["nominal"]["return"] == pytest.approx(nominal.mean_return, rel=1e-6)
    assert rec["nominal"]["normalized"] == pytest.approx(nominal.mean_normalized, rel=1e-6)
    assert rec["final_return"] != pytest.approx(rec["nominal"]["return"])
    # the leaderboard keeps it apart from the nominal runs, and a record's id is its content
    from bench.leaderboard import variant
    from bench.runner import record_run_id
    nominal_rec, _ = execute(nominal_p, store, log=lambda s: None)
    assert "train_dynamics" not in nominal_rec and "nominal" not in nominal_rec
    assert variant(rec) != variant(nominal_rec)
    assert record_run_id(rec) == rec["run_id"]
    assert record_run_id(nominal_rec) == nominal_rec["run_id"]
    # the leaderboard: one row per dynamics, the nominal score beside the headline one
    from bench.leaderboard import board, records_frame, to_markdown
    b = board(records_frame(store))
    rows = {r.dynamics: r for r in b.itertuples()}
    assert set(rows) == {"nominal", "action_bias=0.5:fixed"}
    assert rows["action_bias=0.5:fixed"].normalized_mean == pytest.approx(
        rec["final_normalized"])
    assert rows["action_bias=0.5:fixed"].nominal_mean == pytest.approx(
        rec["nominal"]["normalized"])
    header = to_markdown(b).splitlines()[0]
    assert "| dynamics" in header and "| nominal" in header


def test_cloth_scores_under_its_test_noise_and_refuses_init_noise():
    """The cloth's pipeline state has no joint coordinates: its perturbed env resets (the
    evaluator's path for test_noise) and init_noise is refused by name."""
    task = make_task("cloth")
    env = perturbed_task(task, Perturbation("test_noise", 1.0)).env
    s = env.reset(jax.random.PRNGKey(0))
    np.testing.assert_array_equal(s.obs, task.env.reset(jax.random.PRNGKey(0)).obs)
    with pytest.raises(ValueError, match="no joint coordinates for init_noise"):
        parse_dynamics("init_noise:0.1", task)


def test_a_nominal_store_keeps_its_table_layout(probe, store):
    from bench.leaderboard import board, records_frame, to_markdown
    execute(prepare(_request()), store, log=lambda s: None)
    header = to_markdown(board(records_frame(store))).splitlines()[0]
    assert "dynamics" not in header and "nominal" not in header


def test_cloth_paths_plot_draws_each_run_and_refuses_an_empty_store(store, tmp_path):
    """A cloth record whose trajectory is the demo's own: the plot is written; a store with
    no cloth run is a clear error."""
    from bench.plots import cloth_paths_plot
    from tasks.demo import load_demo
    task = make_task("cloth")
    with pytest.raises(ValueError, match="no finished cloth runs"):
        cloth_paths_plot(store, str(tmp_path / "out"))
    store.write({"run_id": "c0", "task": "cloth", "method": "bc", "seed": 0, "status": "ok",
                 "final_normalized": 1.0,
                 "train_dynamics": Perturbation("test_noise", 1.0, "fixed").describe()})
    store.write_trajectory("c0", load_demo(task.spec.demo_path, task).states[0])
    path = cloth_paths_plot(store, str(tmp_path / "out"))
    assert path.endswith("cloth_paths.png")
    import os
    assert os.path.getsize(path) > 10_000


def test_task_dynamics_resolve_to_each_tasks_calibrated_adaptation_family():
    """`--train-dynamics task` is each task's TaskSpec.adapt at its transfer column's
    magnitude, with the same key (so the same run id) as naming the family."""
    from bench.perturb import parse_dynamics
    from tasks import TASKS, make_task
    hopper = make_task("hopper")
    assert parse_dynamics("task", hopper) == parse_dynamics("actuator", hopper)
    assert parse_dynamics("task", hopper).key == "actuator=-0.3"
    assert parse_dynamics("task", make_task("acrobot")).key == "action_bias=0.2"
    assert parse_dynamics("task", make_task("cloth")).key == "test_noise=1:fixed"
    for name, spec in TASKS.items():  # every declared family is one of its transfer families
        if spec.adapt is not None:
            p = parse_dynamics("task", make_task(name))
            assert (p.family, p.magnitude) in dict(spec.transfer).items(), name
    with pytest.raises(ValueError, match="'pointmass' declares no adaptation dynamics.*"
                                         "tasks that do: inverted_pendulum"):
        parse_dynamics("task", make_task("pointmass"))
