"""The plugin conformance check (bench/conformance.py, `ildbench conform`): every in-repo
method passes it on pointmass, and it catches a method that re-traces its update, one that
is not deterministic and one that overruns its budget."""
import dataclasses

import jax
import jax.numpy as jnp
import pytest

from bench import plugins
from bench.api import MethodSpec, Policy, TrainResult, Uses
from bench.conformance import conform, findings, render

# Small configurations: the checks are about the loop, not the score.
_SB3 = dict(report_every=256, learning_starts=256, updates_per_step=0.25, num_envs=8,
            steps_per_collect=64, batch_size=64)
SMALL = {
    "bc": dict(env_steps=1, overrides=dict(updates=200, chunk=40)),
    "ild": dict(env_steps=8 * 128 * 12, overrides=dict(num_envs=8, hidden="(64, 64)",
                                                       bc_updates=50, updates=12)),
    "shac": dict(env_steps=8 * 32 * 12, overrides=dict(num_envs=8, actor_hidden="32,32",
                                                       critic_hidden="32,32")),
    "dac": dict(env_steps=1536, overrides=_SB3),
    "pwil": dict(env_steps=1536, overrides=dict(_SB3, prefill=512)),
    "cem_mpc": dict(env_steps=1, overrides=dict(population=16, elites=4, iterations=2, horizon=8)),
    "cem_mpc_track": dict(env_steps=1, overrides=dict(population=16, elites=4, iterations=2, horizon=8)),
}


def test_every_in_repo_method_has_a_small_conformance_setting():
    plugins.all_methods()
    in_repo = {n for n, src in plugins._SOURCES.items() if src.startswith("methods/")}
    in_repo |= set(plugins._UNAVAILABLE)  # a folder whose dependency is missing here
    assert "ild" in in_repo and in_repo <= set(SMALL), f"add {sorted(in_repo - set(SMALL))}"


@pytest.mark.parametrize("method", sorted(SMALL))
def test_in_repo_method_conforms(method):
    if method not in plugins.all_methods():
        pytest.skip(f"{method} is not available here: {plugins._UNAVAILABLE.get(method)}")
    found = {f.check: f for f in conform(method, **SMALL[method])}
    report = render(method, list(found.values()))
    assert all(f.passed is not False for f in found.values()), report
    assert found["runs"].passed and found["deterministic"].passed, report
    loop = method not in ("cem_mpc", "cem_mpc_track")  # planners have no training loop
    assert (found["compiles once"].passed is True) == loop, report


# --- planted faults --------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class FaultConfig:
    retrace: bool = False
    """Jit a fresh closure each update (each one a new computation to compile)."""
    weak_metric: bool = False
    """The update writes a Python float into its carried state, as brax's hopper did to
    SHAC: the second update meets a weakly typed leaf and compiles once more."""
    unseeded: bool = False
    overrun: bool = False
    big_update: bool = False
    """One update simulates 5000 env steps: more than twice a 1000-step budget, although
    the method stops when told (ILD's paper preset under conform's default budget)."""


def _act(params, obs, key, deterministic):
    return jnp.clip(-params * obs[..., :1] - obs[..., 1:], -1, 1)


def update(state, weak_metric):
    gain, _ = state
    return gain * 0.999 + 0.002, (1.0 if weak_metric else jnp.float32(1.0))


_update = jax.jit(update, static_argnums=1)
_draws = iter(range(10**6))


def faulty_train(task, demo, config, ctx, seed):
    gain = jnp.float32(2.0 + (next(_draws) * 1e-3 if config.unseeded else 0.0))
    state, steps = (gain, jnp.float32(0.0)), 0
    while config.overrun and steps < 10_000 or not ctx.should_stop(steps):
        if config.retrace:
            def fresh(state, weak_metric):  # a new function object: a new computation
                return update(state, weak_metric)
            step = jax.jit(fresh, static_argnums=1)
        else:
            step = _update
        state = step(state, config.weak_metric)
        steps += 5000 if config.big_update else 100
        ctx.report(Policy(_act, state[0]), steps, {"train/loss": float(state[0])})
    return TrainResult(Policy(_act, state[0]), env_steps=steps)


@pytest.fixture
def faulty(temp_method):
    return temp_method(MethodSpec(name="faulty", train=faulty_train, config_cls=FaultConfig,
                                  uses=Uses()))


def _check(**over):
    return {f.check: f for f in conform("faulty", env_steps=1000, evals=1, overrides=over)}


def test_a_well_behaved_method_passes_and_the_compile_counts_are_exact(faulty):
    found = _check()
    assert [f.passed for f in found.values()] == [True, True, True, True]
    # 1000 env steps at 100 per update: 10 reports; `update` traced once, before the first
    assert "compiled in training over 10 reports, none traced again" in \
        found["compiles once"].detail


def test_a_method_that_retraces_its_update_fails_compiles_once(faulty):
    found = _check(retrace=True)
    assert found["compiles once"].passed is False
    # a fresh closure per update: compiled at updates 2..10, after a report each time
    detail = found["compiles once"].detail
    assert "traced again after a report: fresh (tests/test_conformance.py:" in detail
    assert ") 9x (JAX: never seen function" in detail  # and JAX's word on why
    assert found["runs"].passed and found["deterministic"].passed


def test_one_extra_compile_at_the_second_update_fails_compiles_once(faulty):
    """SHAC's bug: a weakly typed leaf written by the first update makes the
    second compile again, and never again after; one extra compilation is caught."""
    found = _check(weak_metric=True)
    detail = found["compiles once"].detail
    assert found["compiles once"].passed is False
    assert "traced again after a report: update (tests/test_conformance.py:" in detail
    assert ") 1x (JAX: " in detail and "now f32[]{weak_type=True} and before f32[]" in detail


def test_an_unseeded_method_fails_deterministic(faulty):
    found = _check(unseeded=True)
    assert found["deterministic"].passed is False and found["runs"].passed


def test_a_method_that_ignores_should_stop_fails_budget(faulty):
    found = _check(overrun=True)
    assert found["budget"].passed is False
    assert "used 10000 of 1000 env steps" in found["budget"].detail
    assert "call ctx.should_stop(env_steps) before each update" in found["budget"].detail


def test_an_update_bigger_than_the_budget_is_named_as_such(faulty):
    """It stopped when told: the hint is to shrink the update, not to call should_stop."""
    found = _check(big_update=True)
    detail = found["budget"].detail
    assert found["budget"].passed is False and "used 5000 of 1000 env steps" in detail
    assert "simulates 5000 env steps on average" in detail and "--preset cpu" in detail
    assert "should_stop" not in detail


def test_a_failed_run_reports_its_message_and_stops_there():
    rec = {"status": "failed", "final_return": None, "final_normalized": None,
           "message": "RuntimeError: boom\ntraceback"}
    found = findings([rec], 100)
    assert [(f.check, f.passed) for f in found] == [("runs", False)]
    assert "failed: RuntimeError: boom" in found[0].detail


def test_bad_input_is_refused_before_any_run():
    with pytest.raises(plugins.UnknownMethodError):
        conform("no_such_method")
    with pytest.raises(ValueError, match="repeats"):
        conform("bc", repeats=0)


def test_jax_explains_its_cache_misses_through_a_logger_the_meter_watches():
    """The meter filters named loggers (a filter sees only its own logger's records); JAX
    moved the explanations from jax._src.pjit to jax._src.interpreters.partial_eval in 0.10,
    and an unwatched logger means no retrace is ever caught (and the log fills with them)."""
    import logging

    from bench.budget import _CompileMeter

    names = []

    class Catch(logging.Handler):
        def emit(self, record):
            if record.getMessage().startswith("TRACING CACHE MISS"):
                names.append(record.name)

    handler, log = Catch(), logging.getLogger("jax")
    log.addHandler(handler)
    saved = jax.config.jax_explain_cache_misses
    jax.config.update("jax_explain_cache_misses", True)
    try:
        f = jax.jit(lambda x: x * 2.0)
        f(jnp.ones(3)).block_until_ready()
        f(jnp.ones(4)).block_until_ready()      # a new shape: traced again, and explained
    finally:
        jax.config.update("jax_explain_cache_misses", saved)
        log.removeHandler(handler)
    assert names, "no TRACING CACHE MISS explanation was logged under the 'jax' logger"
    assert set(names) <= set(_CompileMeter._LOGGERS), (names, _CompileMeter._LOGGERS)
