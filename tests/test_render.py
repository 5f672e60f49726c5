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
