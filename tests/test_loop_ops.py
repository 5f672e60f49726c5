"""results/substep/scripts/loop_ops.py (session 51) reads a compiled function's loops from its
optimized HLO: each loop's trip count, the operations one pass of its body runs and how many
passes a call makes. Checked on a function whose loops are known by construction, and its
estimate of the operations per call against those XLA's runtime executes under the
profiler."""

import jax
import jax.numpy as jnp
import pytest


@pytest.fixture(scope="module")
def loop_ops(substep_script):
    with substep_script("loop_ops") as mod:
        yield mod


def _nested(x):
    """An outer scan of 5 steps, each running an inner scan of 3; the bodies do work that
    depends on the carry, so XLA keeps both loops."""
    def inner(c, _):
        return jnp.sin(c) * 1.5 + jnp.cos(c[::-1]), None

    def outer(c, _):
        c = jax.lax.scan(inner, c, None, length=3)[0]
        return jnp.tanh(c) + jnp.sort(c), jnp.sum(c)
    return jax.lax.scan(outer, x, None, length=5)


def test_loops_finds_each_loop_its_trips_and_its_passes_per_call(loop_ops):
    hlo = jax.jit(_nested).lower(jnp.arange(8.0)).compile().as_text()
    rows = loop_ops.loops(hlo)
    assert rows[0]["part"] == "entry" and rows[0]["passes"] == 1
    trips = sorted((r["depth"], r["trip"], r["passes"]) for r in rows[1:])
    assert trips == [(1, 5, 5), (2, 3, 15)]  # the inner body runs 5 x 3 times per call
    assert all(r["body_ops"] >= 1 for r in rows)


def test_loops_estimate_is_what_the_runtime_executes(loop_ops):
    """The estimate (sum of body operations x passes) for ILD's update on pointmass against
    the operations XLA's CPU runtime records under the profiler, as op_count.py counts
    them at B = 32 (the tiny function above, and pointmass at B = 8, record few or no
    events: XLA runs small programs' operations outside the profiled executor)."""
    import timing
    from methods.ild.benchmark import speed_setup
    from methods.ild.paired import compiled_chunk, parse_variant
    from tasks import make_task
    task = make_task("pointmass")
    cfg = parse_variant("task", 32, "pointmass")
    chunk, state, one = compiled_chunk(task, cfg, speed_setup(task, cfg))
    rows = loop_ops.loops(chunk.lower(state, one).compile().as_text())
    assert [r["trip"] for r in rows if r["part"] == "forward"] == [task.episode_length]
    estimate = sum(r["body_ops"] * r["passes"] for r in rows)
    def three_calls():
        for _ in range(3):
            jax.block_until_ready(chunk(state, one))
    jax.block_until_ready(chunk(state, one))
    count = timing.xla_op_events(three_calls, skip=("ThunkExecutor", "end: ",
                                                    "ThreadpoolListener"))[1]
    # session 51: 31,786 estimated, 31,732 executed per call (hopper's forward: 175,580
    # both; its update 436,077 and 436,497): an estimate to a few tenths of a percent
    assert 3 * estimate == pytest.approx(sum(count.values()), rel=0.01)
    assert estimate > 20_000  # the 128 steps' bodies are in it, not only the entry
