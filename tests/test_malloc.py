"""bench.malloc: glibc's huge-page tunable for XLA's per-call working memory."""
import json
import os
import subprocess
import sys

import pytest

from bench import cli, malloc


@pytest.fixture
def able(monkeypatch):
    """A machine where the tunable can act: glibc 2.36, transparent huge pages 'madvise'."""
    monkeypatch.setattr(malloc, "glibc_version", lambda: (2, 36))
    monkeypatch.setattr(malloc, "thp_mode", lambda path=malloc.THP_PATH: "madvise")


@pytest.fixture
def execve_calls(monkeypatch):
    """`os.execve` recorded rather than run, as (path, argv, GLIBC_TUNABLES), each call ending
    the caller with SystemExit(0) (execve does not return); the tunable's variables unset."""
    calls = []

    def fake_execve(path, argv, env):
        calls.append((path, argv, env.get("GLIBC_TUNABLES")))
        raise SystemExit(0)

    monkeypatch.setattr(os, "execve", fake_execve)
    for name in ("GLIBC_TUNABLES", "ILDBENCH_HUGEPAGES", "ILDBENCH_HUGEPAGES_SET"):
        monkeypatch.delenv(name, raising=False)
    return calls


def test_env_with_hugepages_adds_the_tunable_once(able, monkeypatch):
    tun, done = "glibc.malloc.hugetlb=1", {"ILDBENCH_HUGEPAGES_SET": "1"}
    assert malloc.env_with_hugepages({"A": "b"}) == {"A": "b", "GLIBC_TUNABLES": tun, **done}
    assert malloc.env_with_hugepages({"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}) == {
        "GLIBC_TUNABLES": "glibc.malloc.arena_max=2:" + tun, **done}
    assert malloc.env_with_hugepages(done) is None  # re-executed once already
    # set already, either way, or turned off: nothing to add
    assert malloc.env_with_hugepages({"GLIBC_TUNABLES": tun}) is None
    assert malloc.env_with_hugepages({"GLIBC_TUNABLES": "x.y=3:glibc.malloc.hugetlb=0"}) is None
    assert malloc.env_with_hugepages({"ILDBENCH_HUGEPAGES": "0"}) is None
    assert malloc.hugetlb({"GLIBC_TUNABLES": "x.y=3:glibc.malloc.hugetlb=0"}) == "0"
    assert malloc.hugetlb({}) is None
    # where it cannot act
    monkeypatch.setattr(malloc, "thp_mode", lambda path=malloc.THP_PATH: "never")
    assert malloc.env_with_hugepages({}) is None
    monkeypatch.setattr(malloc, "thp_mode", lambda path=malloc.THP_PATH: "always")
    assert malloc.env_with_hugepages({}) == {"GLIBC_TUNABLES": tun, **done}
    for version in ((2, 34), None):  # the tunable came with glibc 2.35; not glibc at all
        monkeypatch.setattr(malloc, "glibc_version", lambda v=version: v)
        assert malloc.env_with_hugepages({}) is None


def test_thp_mode_reads_the_bracketed_mode(tmp_path):
    f = tmp_path / "enabled"
    f.write_text("always [madvise] never\n")
    assert malloc.thp_mode(str(f)) == "madvise"
    assert malloc.thp_mode(str(tmp_path / "missing")) is None


def test_ildbench_reexecutes_itself_once_with_the_tunable(able, execve_calls, monkeypatch):
    calls = execve_calls
    monkeypatch.setattr(cli, "main", lambda: 7)
    monkeypatch.setattr(sys, "argv", ["ildbench", "run", "--task", "pointmass"])
    with pytest.raises(SystemExit):
        cli.entry()
    assert calls == [(sys.executable, [sys.executable, "-m", "bench.cli", "run", "--task",
                                       "pointmass"], "glibc.malloc.hugetlb=1")]
    monkeypatch.setattr(sys, "argv", ["results/x/scripts/s.py", "hopper", "--out", "o.csv"])
    with pytest.raises(SystemExit):  # no module: a script under results/ runs itself again
        malloc.reexec_with_hugepages()
    assert calls[-1] == (sys.executable, [sys.executable, "results/x/scripts/s.py", "hopper",
                                          "--out", "o.csv"], "glibc.malloc.hugetlb=1")
    del calls[1:]
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.hugetlb=1")  # the re-executed process
    assert cli.entry() == 7 and len(calls) == 1
    monkeypatch.delenv("GLIBC_TUNABLES")
    monkeypatch.setenv("ILDBENCH_HUGEPAGES", "0")
    assert cli.entry() == 7 and len(calls) == 1


_UPDATES = r"""
import hashlib, json, resource
import jax, numpy as np
from benchmarks.ild_speed import speed_setup
from methods.ild.config import ILDConfig
from methods.ild.train import initial_state, make_chunk, make_update
from tasks import make_task
task = make_task("pointmass")
cfg = ILDConfig(num_envs=128)
policy, goals, norm, params, k = speed_setup(task, cfg)
update, opt, _ = make_update(task, policy, goals, norm, cfg, k[2])
chunk, state = make_chunk(update, 1), initial_state(params, opt, k[3], cfg)
temp = chunk.lower(state, np.int32(1)).compile().memory_analysis().temp_size_in_bytes
state = jax.block_until_ready(chunk(state, np.int32(1))[0])  # compiles
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(3):
    state = jax.block_until_ready(chunk(state, np.int32(1))[0])
faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults) / 3
leaves = np.concatenate([np.ravel(x) for x in jax.tree.leaves(state.params)])
print(json.dumps({"temp_mib": temp / 2**20, "faults": faults,
                  "sha": hashlib.sha256(leaves.tobytes()).hexdigest()}))
"""


def _updates(tunables: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    if tunables:
        env["GLIBC_TUNABLES"] = tunables
    out = subprocess.run([sys.executable, "-c", _UPDATES], env=env, capture_output=True,
                         text=True, timeout=600, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # a hopper update compiled in two processes
@pytest.mark.skipif(malloc.env_with_hugepages({}) is None,
                    reason="glibc's huge-page tunable cannot act on this machine")
def test_hugepages_spare_an_update_its_page_faults_and_change_no_number():
    """Four ILD updates on pointmass (B = 128: ~57 MiB of backward-pass residuals per call;
    at B = 32 `swish_remat` keeps it at 14 MiB, under the threshold),
    in a process without and one with the tunable: the same parameters bit for bit, and
    (where the kernel's huge pages are 'madvise', so only the tunable asks for them) a
    fraction of the page faults per call."""
    plain, huge = _updates(None), _updates("glibc.malloc.hugetlb=1")
    assert plain["sha"] == huge["sha"]
    assert plain["temp_mib"] > 32  # above glibc's largest mmap threshold: mapped per call
    if malloc.thp_mode() == "madvise":
        assert plain["faults"] > 0.8 * plain["temp_mib"] * 256  # a fault per 4 KiB page
        assert huge["faults"] < plain["faults"] / 10


def test_python_m_bench_cli_reexecutes_as_ildbench_does(able, execve_calls, monkeypatch):
    """`python -m bench.cli` takes `ildbench`'s path (`entry`), huge-page tunable included:
    run as `main` alone, sweeps started that way would run without the tunable the other
    cells had."""
    import runpy
    import warnings
    monkeypatch.setattr(sys, "argv", ["/somewhere/bench/cli.py", "tasks"])
    with warnings.catch_warnings(), pytest.raises(SystemExit):
        warnings.simplefilter("ignore", RuntimeWarning)  # bench.cli is imported already
        runpy.run_module("bench.cli", run_name="__main__")
    assert execve_calls == [(sys.executable, [sys.executable, "-m", "bench.cli", "tasks"],
                             "glibc.malloc.hugetlb=1")]
