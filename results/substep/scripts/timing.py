"""The timing and profiling the step-VJP scripts beside it share (run them as scripts: this
folder is then on the import path); their VJP of ones is `methods.ild.benchmark.vjp_of_ones`,
the benchmark's own."""
from __future__ import annotations

import collections
import glob
import re
import tempfile
import time

import jax


def best_seconds(f, *args, calls: int = 50, rounds: int = 3) -> float:
    """Seconds per call of `f(*args)`: compiled and run once first, then the minimum over
    `rounds` rounds of `calls` calls."""
    jax.block_until_ready(f(*args))
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(calls):
            jax.block_until_ready(f(*args))
        best = min(best, (time.perf_counter() - t0) / calls)
    return best


def interleaved_seconds(programs: dict, rounds: int, calls: int) -> dict[str, list[float]]:
    """{name: seconds per call in each round} for programs {name: (f, args)}: every program
    is run once first (compiled), then `rounds` rounds each time every program over `calls`
    calls in turn, after a warm-up round that is not kept."""
    for f, args in programs.values():
        jax.block_until_ready(f(*args))
    seconds = {name: [] for name in programs}
    for _ in range(rounds + 1):
        for name, (f, args) in programs.items():
            t0 = time.perf_counter()
            for _ in range(calls):
                jax.block_until_ready(f(*args))
            seconds[name].append((time.perf_counter() - t0) / calls)
    return {name: s[1:] for name, s in seconds.items()}


def op_kind(name: str) -> str:
    """An XLA operation's kind: its name without the number (`dot_general.12` ->
    `dot_general`)."""
    return re.sub(r"\.\d+$", "", name)


def xla_op_events(run, skip=("ThunkExecutor",), by_name: bool = False):
    """(nanoseconds, events) by operation kind (the event's name without its number; with
    `by_name`, by the name itself: one entry per operation) that XLA's CPU runtime threads
    record while `run()` runs under `jax.profiler.trace`; events whose names start with one
    of `skip` are left out (the executor's own by default)."""
    time_ns, count = collections.Counter(), collections.Counter()
    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d):
            run()
        data = jax.profiler.ProfileData.from_file(
            glob.glob(d + "/**/*.xplane.pb", recursive=True)[0])
        for plane in data.planes:
            for line in plane.lines:
                if "XLA" not in line.name:  # the runtime's threads, not Python's
                    continue
                for ev in line.events:
                    if ev.name.startswith(skip):
                        continue
                    kind = ev.name if by_name else op_kind(ev.name)
                    time_ns[kind] += ev.duration_ns
                    count[kind] += 1
    return time_ns, count


def states_in(task, batch: int, steps: int = 10, action: float = 0.3):
    """(pipeline_state, actions) of `batch` envs of brax task `task`, `steps` control steps
    after reset under the constant `action` (contacts active): where the step scripts time."""
    import jax.numpy as jnp
    env = task.env.unwrapped
    step = jax.jit(jax.vmap(env.step))
    s = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))
    act = jnp.full((batch, task.action_size), action)
    for _ in range(steps):
        s = step(s, act)
    return s.pipeline_state, act


def forward_and_vjp_seconds(f, *args, calls: int = 100) -> tuple[float, float]:
    """Seconds per call of jit(vmap(f)) and of its VJP with a cotangent of ones
    (`methods.ild.benchmark.vjp_of_ones`), each by `best_seconds`."""
    from methods.ild.benchmark import vjp_of_ones
    vf = jax.vmap(f)
    return (best_seconds(jax.jit(vf), *args, calls=calls),
            best_seconds(jax.jit(vjp_of_ones(vf)), *args, calls=calls))


def print_forward_and_vjp(forms: dict, *args, width: int = 34) -> None:
    """For each name -> f in `forms`: `forward_and_vjp_seconds(f, *args)` printed as one line
    (microseconds forward, as a VJP, and their ratio)."""
    for name, f in forms.items():
        fwd, back = forward_and_vjp_seconds(f, *args)
        print(f"{name:{width}s} forward {fwd * 1e6:8.1f} us   vjp {back * 1e6:8.1f} us   "
              f"vjp / forward {back / fwd:5.2f}", flush=True)
