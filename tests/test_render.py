"""HTML renders from matched states (brax viewer)."""
import numpy as np
import pytest

from bench.render import render_pair, states_from_matched, viewer_html
from tasks import make_task
from tasks.core import brax_matched_state
from tasks.demo import load_demo


def test_matched_states_decode_to_the_pipeline_transforms():
    import jax
    task = make_task("hopper")
    s = task.env.reset(jax.random.PRNGKey(3))
    m = np.asarray(brax_matched_state(s.pipeline_state))[None]
    (st,) = states_from_matched(m, task.env.unwrapped.sys.num_links())
    np.testing.assert_array_equal(st.x.pos, np.asarray(s.pipeline_state.x.pos))
    np.testing.assert_array_equal(st.x.rot, np.asarray(s.pipeline_state.x.rot))
    with pytest.raises(ValueError, match="do not fit 4 bodies"):
        states_from_matched(m[:, :-1], 4)


def test_render_pair_writes_both_viewers_and_is_linked(store, tmp_path):
    from bench import leaderboard as lb
    task = make_task("hopper")
    demo = load_demo(task.spec.demo_path, task)
    store.write({"run_id": "r0", "task": "hopper", "method": "bc", "seed": 0, "status": "ok",
                 "final_normalized": 0.9, "final_return": 300.0, "finished": "x",
                 "uses": {"demo_states": True}, "reference_method": False,
                 "budget": {"seconds": 60.0, "env_steps": None, "charge_compile": True,
                            "evals": 10}})
    with pytest.raises(ValueError, match="with a stored trajectory"):
        render_pair(store, "hopper", "bc", str(tmp_path))
    store.write_trajectory("r0", demo.states[0][::-1])  # any (T+1, S) states will do
    path = render_pair(store, "hopper", "bc", str(tmp_path))
    page = open(path).read()
    assert path.endswith("render_hopper_bc.html")
    assert page.count("<iframe srcdoc=") == 2 and "normalized 0.900" in page
    lb.write(lb.leaderboard(store), str(tmp_path))
    assert "[hopper_bc](render_hopper_bc.html)" in open(tmp_path / "leaderboard.md").read()
    with pytest.raises(ValueError, match="no brax system"):
        viewer_html("pointmass", np.zeros((3, 2)))


def _cloth_record(store, run_id, method, seed, score, key, states):
    dyn = None if key is None else {"family": "test_noise", "magnitude": 1.0, "key": key,
                                    "noise": "fixed" if key.endswith("fixed") else "fresh"}
    store.write({"run_id": run_id, "task": "cloth", "method": method, "seed": seed,
                 "status": "ok", "final_normalized": score, "final_return": score,
                 "finished": "x", "train_dynamics": dyn, "uses": {"demo_states": True},
                 "reference_method": False,
                 "budget": {"seconds": 60.0, "env_steps": None, "charge_compile": True,
                            "evals": 10}})
    if states is not None:
        store.write_trajectory(run_id, states)


def test_cloth_render_animates_the_demo_beside_each_methods_best_run(store, tmp_path):
    from bench.render import _cloth_frames, cloth_panels, render_cloth
    task = make_task("cloth")
    demo = np.asarray(load_demo(task.spec.demo_path, task).states[0])
    fixed, fresh = "test_noise=1:fixed", "test_noise=1"
    _cloth_record(store, "a", "ild", 0, 0.0, fixed, demo)
    _cloth_record(store, "b", "ild", 1, 1.0, fixed, demo[:40])  # ended early: padded
    _cloth_record(store, "c", "ild", 2, 1.0, fixed, demo)       # tie: the lower seed shows
    _cloth_record(store, "d", "bc", 0, 0.0, fixed, demo)
    _cloth_record(store, "e", "ild", 0, 0.0, fresh, demo)
    _cloth_record(store, "f", "dac", 0, 0.5, None, None)        # no trajectory: not drawn
    panels = [(d, m, r["run_id"]) for d, m, r in cloth_panels(store)]
    assert panels == [(fresh, "ild", "e"), (fixed, "bc", "d"), (fixed, "ild", "b")]
    assert [p[2]["run_id"] for p in cloth_panels(store, ["ild"], seed=0)] == ["e", "a"]
    with pytest.raises(ValueError, match="no finished cloth run of dac with a stored"):
        cloth_panels(store, ["ild", "dac"])
    padded = _cloth_frames(demo[:40], len(demo))
    assert padded.shape == demo.shape
    np.testing.assert_array_equal(padded[:40], demo[:40])
    np.testing.assert_array_equal(padded[40:], np.repeat(demo[39:40], len(demo) - 40, 0))
    path = render_cloth(store, str(tmp_path / "out"), every=8)
    page = open(path).read()
    assert path.endswith("render_cloth.html")
    frames = -(-len(demo) // 8)
    assert page.count("data:image/png;base64") == frames  # one image per shown frame
    assert "<script" in page and "cloth: the expert demo" in page


def test_render_of_a_brax_task_needs_exactly_one_method(tmp_path):
    from bench.cli import main
    assert main(["render", "--task", "hopper", "--store", str(tmp_path / "runs")]) == 2
    assert main(["render", "--task", "hopper", "--method", "bc", "ild",
                 "--store", str(tmp_path / "runs")]) == 2
