"""The physics plan (`tasks.physics.plan`): each task's exact-equivalent rewrites of brax's
step, handed to every method that differentiates through the physics, and `--physics
reference` to run brax's step instead."""
import dataclasses

import jax
import jax.numpy as jnp
import pytest

from bench.api import MethodSpec, Policy, TrainResult, Uses
from bench.budget import Budget
from bench.evaluator import EvalConfig
from bench.runner import RunRequest, execute, prepare, record_run_id
from tasks import make_task
from tasks.physics import CHOICES, PLANS, REFERENCE, Plan, plan_for
from tasks.physics import transforms as tr
from tasks.physics.spring_adjoint import only_hinges, planar_roots, rotary_joints
from tasks.registry import TASKS


def test_each_rewrite_is_in_a_cpu_plan_exactly_where_the_scene_fits_it():
    """On a CPU every task's plan takes each rewrite wherever the task's scene fits it (its
    `*_refusal` has no objection) and nowhere else: lean substeps on brax's spring and
    positional tasks with motors; the hand-written spring VJPs on the spring tasks, with
    hinge forces where every 1-dof joint is a hinge, planar roots and rotary joints where
    the scene has them; the positional joints, the planar backward (reacher's with its
    normal gravity dropped, where it needs that), the links' form in 3-D and the closed
    form wherever they fit; small products only on swimmer (the generalized step they
    speed up; the closed form replaces acrobot's). Planted fault: a task's row losing a
    rewrite, or naming one its scene refuses."""
    plans = {name: plan_for(name, "cpu") for name in TASKS}
    tasks = {name: make_task(name) for name in TASKS}

    def where(field):
        return {name for name, p in plans.items() if getattr(p, field)}

    def fits(refusal, **kw):
        return {name for name, t in tasks.items() if refusal(t, **kw) is None}
    assert where("lean_substeps") == fits(tr.lean_substeps_refusal)
    assert where("hand_adjoint") == fits(tr.hand_adjoint_refusal) == {
        "hopper", "walker2d", "ant", "humanoid"}
    spring = where("hand_adjoint")
    sys_of = {name: tasks[name].env.unwrapped.sys for name in spring}
    assert where("hinge_forces") == {n for n in spring if only_hinges(sys_of[n])}
    assert where("planar_root") == {n for n in spring if planar_roots(sys_of[n]) is not None}
    assert where("rotary_joints") == {n for n in spring if rotary_joints(sys_of[n])}
    assert where("positional_joints") == fits(tr.positional_joints_refusal)
    assert where("planar_adjoint") == fits(tr.planar_adjoint_refusal, drop_normal_gravity=True)
    assert where("planar_normal_gravity") == (
        where("planar_adjoint") - fits(tr.planar_adjoint_refusal)) == {"reacher"}
    assert where("planar_links") == {n for n in where("planar_adjoint") if n in spring}
    assert where("spatial_links") == fits(tr.spatial_adjoint_refusal) == {"ant", "humanoid"}
    assert where("closed_form_adjoint") == {n for n, t in tasks.items()
                                            if tr.has_closed_form_adjoint(t)} == {"acrobot"}
    assert where("small_dots") == {"swimmer"}
    assert where("saved_residuals") == {"ant", "humanoid"}
    assert all(p.substep_remat for p in plans.values())


def test_a_gpu_plan_drops_the_cpu_only_rewrites_of_ant_and_humanoid():
    """The hand-written spring VJPs and the links' form cut XLA's operation count, which is
    what an update costs on one CPU core; on a GPU ant and humanoid differentiate brax's
    spring substep by reverse mode (lean substeps kept), every other task runs its CPU
    plan, and a TPU runs the GPU's. A task without a row runs `Plan()`."""
    for name in TASKS:
        cpu, gpu = plan_for(name, "cpu"), plan_for(name, "gpu")
        if name in ("ant", "humanoid"):
            assert gpu == Plan(lean_substeps=True) != cpu
        else:
            assert gpu == cpu, name
        assert plan_for(name, "tpu") == gpu
    assert plan_for("a_plugin_task", "cpu") == Plan() == plan_for("a_plugin_task", "gpu")
    assert set(PLANS) <= set(TASKS)


def test_plan_identity_and_validation():
    """A plan enters a run id as the fields that differ from `Plan()`, under their names
    (where the rewrites were config fields, so the committed ids hold); a combination of
    rewrites that cannot compose is refused naming the fields and the fix."""
    assert Plan().identity() == {}
    assert REFERENCE.identity() == {"substep_remat": False}
    assert plan_for("acrobot", "cpu").identity() == {"closed_form_adjoint": True}
    assert plan_for("hopper", "cpu").acting() == (
        "lean_substeps", "hand_adjoint", "hinge_forces", "planar_root", "planar_adjoint",
        "planar_links")  # substep_remat: nothing to rematerialize under a planar backward
    assert Plan().acting(substep_loop=False) == ()
    for bad, match in (({"hinge_forces": True}, "hinge_forces is a piece of hand_adjoint"),
                       ({"planar_adjoint": True, "spatial_links": True}, "all but one"),
                       ({"planar_links": True}, "set planar_adjoint True"),
                       ({"positional_joints": True, "hand_adjoint": True},
                        "set positional_joints False")):
        with pytest.raises(ValueError, match=match):
            Plan(**bad)
    assert CHOICES == ("task", "reference")


@dataclasses.dataclass(frozen=True)
class _Config:
    pass


def _probe(seen):
    def train(task, demo, config, ctx, seed):
        seen.append((task.plan, "pipeline_step" in vars(task.env.unwrapped)))
        return TrainResult(Policy(lambda p, o, k, d: jnp.zeros(o.shape[:-1] + (1,)), 0.0),
                           env_steps=1)
    return train


@pytest.mark.parametrize("sim_gradients", [True, False])
def test_the_runner_hands_a_differentiating_plugin_the_plans_env(temp_method, store,
                                                                 sim_gradients):
    """A plugin that declares `sim_gradients` gets inverted_pendulum's env with the task's
    plan applied (its own pipeline_step: the planar backward), `--physics reference` brax's
    step; its record says which, and the plan enters its run id. A plugin that does not
    declare it steps the task itself, whatever `--physics` says, and its run id does not
    move. Planted fault: execute() building the view without the plan."""
    seen = []
    temp_method(MethodSpec(name="probe_plan", train=_probe(seen), config_cls=_Config,
                           uses=Uses(demo_states=True, sim_gradients=sim_gradients)))
    recs = []
    for physics in ("task", "reference"):
        p = prepare(RunRequest(method="probe_plan", task="inverted_pendulum", seed=0,
                               budget=Budget(env_steps=1, evals=1),
                               eval=EvalConfig(num_episodes=2), physics=physics))
        rec, skipped = execute(p, store, log=lambda s: None)
        assert rec["status"] == "ok", rec["message"]
        assert record_run_id(rec) == rec["run_id"]
        recs.append((rec, skipped))
    if sim_gradients:
        assert seen == [(plan_for("inverted_pendulum", "cpu"), True), (REFERENCE, False)]
        assert [r["physics"]["choice"] for r, _ in recs] == ["task", "reference"]
        assert recs[0][0]["physics"]["plan"]["planar_adjoint"] is True
        assert recs[0][0]["run_id"] != recs[1][0]["run_id"] and not recs[1][1]
    else:  # one cell: the second request finds the first's record
        assert seen == [(None, False)] and recs[1][1]
        assert "physics" not in recs[0][0] and recs[0][0]["run_id"] == recs[1][0]["run_id"]


def test_an_unknown_physics_choice_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown physics choice 'fast'; choose one of task, "
                                         "reference"):
        prepare(RunRequest(method="ild", task="pointmass", seed=0,
                           budget=Budget(env_steps=100), physics="fast"))


@pytest.mark.parametrize("task", [
    "pointmass",
    # two 128-step full-BPTT updates compiled: about 2 minutes on one core
    pytest.param("inverted_pendulum", marks=pytest.mark.slow)])
def test_reference_physics_gives_the_same_update_and_final_score_to_round_off(task, store):
    """ILD trained one update (after a short BC warm start) on the task's plan and on brax's
    step: the same raw gradient norm and the same final evaluation return to float32
    round-off, since the plan changes what a gradient costs, not what it is (pointmass's
    plan changes nothing: the same numbers exactly). inverted_pendulum runs without ILD's
    per-step gradient normalization: that normalization takes each step's cotangent norm
    field by field over the state, and a whole-step backward (here the planar one) puts the
    cotangent on fewer fields than brax's reverse mode, so where a norm exceeds 1 the two
    are clipped differently (docs/physics.md). Planted fault: a rewrite whose gradient is
    off by a factor."""
    out = {}
    overrides = {"num_envs": 4, "bc_updates": 20, "lr_schedule": "constant"}
    if task == "inverted_pendulum":
        overrides["grad_normalization"] = False
    for physics in ("task", "reference"):
        p = prepare(RunRequest(
            method="ild", task=task, seed=0, budget=Budget(env_steps=4 * 128, evals=1),
            overrides=overrides, eval=EvalConfig(num_episodes=4), physics=physics))
        rec, _ = execute(p, store, log=lambda s: None)
        assert rec["status"] == "ok", rec["message"]
        assert rec["train_metrics"]["train/updates"] == 1
        out[physics] = rec
    task_rec, ref = out["task"], out["reference"]
    norms = [r["train_metrics"]["grad/norm_raw"] for r in (task_rec, ref)]
    assert norms[0] > 1e-3
    if task == "pointmass":
        assert task_rec["final_return"] == ref["final_return"] and norms[0] == norms[1]
    else:
        assert norms[0] == pytest.approx(norms[1], rel=1e-3)
        assert task_rec["final_return"] == pytest.approx(ref["final_return"], rel=1e-3)
    assert jax.default_backend() == task_rec["physics"]["platform"]


def test_shac_actor_gradient_on_the_plan_is_brax_steps():
    """SHAC on acrobot's plan (the closed-form backward) against brax's step: the actor's
    loss over an 8-step window of 4 actors the same bit for bit (brax's step computes the
    forward either way) and every gradient leaf within 1e-4 of its largest entry (SHAC
    rescales no cotangent, so the plan's gradient is brax's). Planted fault: a plan whose
    backward drops the reward's path through the joint velocities."""
    from methods.shac.config import SHACConfig
    from methods.shac.train import SHAC
    from tasks.physics import apply
    cfg = SHACConfig(num_envs=4, horizon=8)
    out = []
    for plan in (REFERENCE, plan_for("acrobot", "cpu")):
        task = apply(make_task("acrobot"), plan)
        agent = SHAC(task.env, task.obs_size, task.action_size, task.episode_length, cfg)
        s = agent.init(jax.random.PRNGKey(0))
        out.append(jax.jit(jax.value_and_grad(lambda a: agent.actor_loss(a, s)[0]))(s.actor))
    (want_l, want), (got_l, got) = out
    assert float(got_l) == float(want_l)
    flat = jax.tree_util.tree_flatten_with_path(want)[0]
    for (path, w), g in zip(flat, jax.tree_util.tree_leaves(got)):
        scale = float(jnp.abs(w).max())
        assert float(jnp.abs(g - w).max()) <= 1e-4 * scale, jax.tree_util.keystr(path)
    assert float(jnp.abs(want["logstd"]).sum()) > 0
