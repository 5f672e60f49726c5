import os
import warnings

import pytest

warnings.filterwarnings("ignore", message="Brax System, piplines")


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
