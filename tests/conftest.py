import os
import warnings

import pytest

warnings.filterwarnings("ignore", message="Brax System, piplines")


def pytest_configure(config):
    """Pin each pytest-xdist worker to a CPU of its own.

    Without this, both workers see every CPU: torch starts one intra-op thread per usable
    CPU (bench.runner.set_torch_threads) and XLA one compile/run thread per CPU, so a torch
    test on one worker stalls behind the other worker's XLA compile. Measured on a 2-core
    Xeon: DAC's and PWIL's pointmass conformance tests took 169 s and 177 s
    beside test_hand_adjoint, 7 s and 5 s alone; test_conformance + test_hand_adjoint +
    test_sb3 took 351 s unpinned and 179 s pinned. With one CPU each, every library sizes
    its pools to 1 and the workers stop competing. Only when there are at least as many
    CPUs as workers; a single process (no -n) keeps every CPU.
    """
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if not worker.startswith("gw") or not hasattr(os, "sched_setaffinity"):
        return
    cpus = sorted(os.sched_getaffinity(0))
    if 1 < count <= len(cpus):
        os.sched_setaffinity(0, {cpus[int(worker[2:]) % len(cpus)]})


@pytest.fixture(scope="session", autouse=True)
def _jax_cache(tmp_path_factory):
    # A per-session persistent compilation cache: repeated shapes within the run compile once.
    from bench.runner import enable_compilation_cache
    enable_compilation_cache(os.environ.get("ILDBENCH_JAX_CACHE") or
                             str(tmp_path_factory.mktemp("jax_cache")))


@pytest.fixture
def store(tmp_path):
    from bench.store import Store
    return Store(str(tmp_path / "runs"))


@pytest.fixture
def weak_metric():
    """A brax wrapper that writes a Python float to a metric on every step, as brax's hopper
    does with `reward_healthy`: the stepped state comes back weakly typed where reset's was
    not (a jitted step carrying it compiles twice)."""
    import jax.numpy as jnp
    from brax.envs.base import Wrapper

    class WeakMetric(Wrapper):
        def reset(self, rng):
            s = self.env.reset(rng)
            return s.replace(metrics={**s.metrics, "healthy": jnp.zeros(())})

        def step(self, state, action):
            s = self.env.step(state, action)
            return s.replace(metrics={**s.metrics, "healthy": 1.0})

    return WeakMetric


@pytest.fixture
def avals():
    """A pytree's type signature as jit sees it: (shape, dtype, weak_type) per leaf."""
    import jax
    return lambda tree: [(x.shape, x.dtype, x.weak_type) for x in jax.tree.leaves(tree)]


@pytest.fixture
def temp_method(monkeypatch):
    """Register a MethodSpec for this test only: temp_method(spec) -> spec."""
    from bench import plugins

    def register(spec):
        plugins.all_methods()  # load the real ones first, so the test's spec is not reloaded
        monkeypatch.setitem(plugins._REGISTRY, spec.name, spec)
        monkeypatch.setitem(plugins._SOURCES, spec.name, "test")
        return spec
    return register


@pytest.fixture
def apg_timed(monkeypatch):
    """benchmarks.ild_speed with brax's APG stubbed out: every task has a reward gradient
    and an APG row reports 1000 env-steps/s. The list it returns gets, per APG row timed,
    whether that row's env runs a rewritten physics step (its own pipeline_step)."""
    from benchmarks import ild_speed as benchmark
    timed = []
    monkeypatch.setattr(benchmark, "reward_gradient_norm", lambda task: 1.0)
    monkeypatch.setattr(benchmark, "_apg_sps", lambda task, batch, hidden, repeats: (
        timed.append("pipeline_step" in vars(task.env.unwrapped)) or 1000.0))
    return timed
