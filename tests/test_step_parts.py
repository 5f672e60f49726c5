"""results/substep/scripts/positional_step_parts.py (session 64): the positional substep's
pieces, each vmapped and jitted alone, by XLA operations (`--ops`). Checked on
inverted_pendulum at B = 2: the pieces compile and run on a rollout's state, a VJP runs
more operations than its forward, and the position update more than the joints' update it
holds."""
import jax
import pytest


@pytest.mark.slow  # four compilations of positional pieces and their VJPs: ~1 minute
def test_step_parts_counts_each_piece_and_the_position_update_holds_the_joints(
        substep_script):
    import tasks.positional_joints as P
    from tasks import make_task
    with substep_script("positional_step_parts") as sp:
        from timing import states_in  # the script's neighbour, on the path while in use
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
