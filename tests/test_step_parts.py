"""results/positional_joints/scripts/step_parts.py (session 64): the positional substep's
pieces, each vmapped and jitted alone, by XLA operations (`--ops`). Checked on
inverted_pendulum at B = 2: the pieces compile and run on a rollout's state, a VJP runs
more operations than its forward, and the position update more than the joints' update it
holds."""
import importlib.util
import pathlib
import sys

import jax
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


SCRIPTS = ROOT / "results" / "substep" / "scripts"


def _step_parts():
    """The script as a module (it puts results/substep/scripts on the import path for its
    neighbours `timing` and `loop_ops`; taken off again by the test)."""
    spec = importlib.util.spec_from_file_location(
        "step_parts", ROOT / "results" / "positional_joints" / "scripts" / "step_parts.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow  # four compilations of positional pieces and their VJPs: ~1 minute
def test_step_parts_counts_each_piece_and_the_substep_holds_them():
    before = list(sys.path)
    try:
        _check(_step_parts())
    finally:
        sys.path[:] = before


def _check(sp):
    import tasks.positional_joints as P
    from tasks import make_task
    from timing import states_in
    task = make_task("inverted_pendulum")
    sys_ = task.env.unwrapped.sys
    ps, act = states_in(task, 2, steps=2)
    parts = sp.pieces(sys_, P.joint_rows(sys_))
    assert list(parts)[-1] == "one whole substep (hand)" and len(parts) == 12
    keep = ("project_xd", "joint_update", "position_update (hand)")
    for name in keep:  # each runs on the batch and gives finite values
        out = jax.jit(jax.vmap(parts[name]))(ps, act)
        assert all(bool(jax.numpy.isfinite(v).all()) for v in jax.tree.leaves(out)), name
    counts = sp.op_counts({k: parts[k] for k in keep}, ps, act)
    for name, (fwd, vjp) in counts.items():
        assert 1 <= fwd < vjp, (name, fwd, vjp)
    # the position update holds the joints' update (and world_to_joint, the corrections)
    assert counts["position_update (hand)"][0] > counts["joint_update"][0]
    assert counts["position_update (hand)"][1] > counts["joint_update"][1]
