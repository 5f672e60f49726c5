"""Compute budgets, the method's clock (paused during harness evaluation) and compile time.

Compile time is measured from JAX's own monitoring events (tracing, lowering and backend
compilation), separately for training and for harness evaluation. By default it counts
against the budget (it is part of what a user waits for; with the persistent compilation
cache a repeated configuration pays little of it); `charge_compile=False` excludes it.
"""
from __future__ import annotations

import contextlib
import dataclasses
import re
import time

import jax

_COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                   "/jax/core/compile/jaxpr_to_mlir_module_duration",
                   "/jax/core/compile/backend_compile_duration")
# One lowering per compiled computation (a jit cache miss, or an eager op on a new shape),
# fired whether or not the persistent cache then supplies the executable.
_LOWERING_EVENT = "/jax/core/compile/jaxpr_to_mlir_module_duration"


class BudgetError(ValueError):
    pass


@dataclasses.dataclass(frozen=True)
class Budget:
    """Wall-clock seconds of training (primary) and/or simulated env steps (deterministic)."""

    seconds: float | None = None
    env_steps: int | None = None
    charge_compile: bool = True
    evals: int = 10
    """How many harness evaluations to spread over the budget (plus the final one)."""

    def __post_init__(self):
        if self.seconds is None and self.env_steps is None:
            raise BudgetError("a budget needs seconds (e.g. --budget 300s) or env steps "
                              "(--budget-steps N)")
        if self.seconds is not None and not self.seconds > 0:
            raise BudgetError(f"budget seconds must be > 0, got {self.seconds}")
        if self.env_steps is not None and not self.env_steps > 0:
            raise BudgetError(f"budget env steps must be > 0, got {self.env_steps}")
        if self.evals < 1:
            raise BudgetError(f"budget evals must be >= 1, got {self.evals}")

    def describe(self) -> str:
        parts = []
        if self.seconds is not None:
            parts.append(f"{self.seconds:g}s")
        if self.env_steps is not None:
            parts.append(f"{self.env_steps} env steps")
        return " / ".join(parts)


def parse_seconds(text: str) -> float:
    """'300', '300s', '10m', '1.5h' -> seconds."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([smh]?)\s*", str(text))
    if not m:
        raise BudgetError(f"cannot read budget {text!r}; write e.g. 300s, 10m or 1h")
    return float(m.group(1)) * {"": 1, "s": 1, "m": 60, "h": 3600}[m.group(2)]


class _CompileMeter:
    """Sums JAX compile-event durations, and counts compilations (lowerings), into whichever
    clock and bucket are active."""

    def __init__(self):
        self.active: Clock | None = None
        self.bucket = "train"
        jax.monitoring.register_event_duration_secs_listener(self._on_event)

    def _on_event(self, event: str, duration: float, **_):
        clock = self.active
        if clock is None or event not in _COMPILE_EVENTS:
            return
        clock.compile_s[self.bucket] = clock.compile_s.get(self.bucket, 0.0) + duration
        if event == _LOWERING_EVENT:
            clock.compiles[self.bucket] = clock.compiles.get(self.bucket, 0) + 1


_METER = _CompileMeter()


class Clock:
    """Training clock: wall time minus paused time (and minus compile time if not charged)."""

    def __init__(self, charge_compile: bool = True):
        self.charge_compile = charge_compile
        self.compile_s = {"train": 0.0, "eval": 0.0}
        self.compiles = {"train": 0, "eval": 0}
        """Computations compiled (JAX lowerings) while training / while the harness worked."""
        self._start = time.perf_counter()
        self._paused = 0.0
        _METER.active = self
        _METER.bucket = "train"

    def elapsed(self) -> float:
        t = time.perf_counter() - self._start - self._paused
        return t if self.charge_compile else t - self.compile_s["train"]

    @contextlib.contextmanager
    def paused(self):
        t0 = time.perf_counter()
        _METER.bucket = "eval"
        try:
            yield
        finally:
            _METER.bucket = "train"
            self._paused += time.perf_counter() - t0

    def close(self):
        if _METER.active is self:
            _METER.active = None
