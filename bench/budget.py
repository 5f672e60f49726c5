"""Compute budgets, the method's clock (paused during harness evaluation) and compile time.

Compile time is measured from JAX's own monitoring events (tracing, lowering and backend
compilation), separately for training and for harness evaluation. By default it counts
against the budget (it is part of what a user waits for; with the persistent compilation
cache a repeated configuration pays little of it); `charge_compile=False` excludes it.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
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
        # One cell, one run id: 600 and 600.0 seconds (or 1e5 and 100000 steps) are the same
        # budget, and the run id hashes these values as JSON.
        if self.seconds is not None:
            object.__setattr__(self, "seconds", float(self.seconds))
        if self.env_steps is not None:
            if self.env_steps != int(self.env_steps):
                raise BudgetError(f"budget env steps must be a whole number, got "
                                  f"{self.env_steps}")
            object.__setattr__(self, "env_steps", int(self.env_steps))

    def describe(self) -> str:
        parts = []
        if self.seconds is not None:
            parts.append(f"{self.seconds:g}s")
        if self.env_steps is not None:
            parts.append(f"{self.env_steps} env steps")
        return " / ".join(parts)


def format_steps(n: float) -> str:
    """Env steps as the tables and progress lines print them: 950, 51k, 20.48M."""
    return f"{n / 1e6:.2f}M" if n >= 1e6 else (f"{n / 1e3:.0f}k" if n >= 1e4 else f"{n:.0f}")


def parse_seconds(text: str) -> float:
    """'300', '300s', '10m', '1.5h' -> seconds."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([smh]?)\s*", str(text))
    if not m:
        raise BudgetError(f"cannot read budget {text!r}; write e.g. 300s, 10m or 1h")
    return float(m.group(1)) * {"": 1, "s": 1, "m": 60, "h": 3600}[m.group(2)]


class _CompileMeter:
    """Sums JAX compile-event durations, and counts compilations (lowerings), into whichever
    clock and bucket are active; and, while a clock is active, reads JAX's own explanations
    of its tracing-cache misses (`jax_explain_cache_misses`) to find a training function
    traced again after a report (`Clock.retraced`). The explanations are consumed here, not
    printed; the flag is restored when the clock closes."""

    _DROP = ("TRACING CACHE MISS", "PERSISTENT COMPILATION CACHE MISS", "Writing ",
             "Not writing persistent cache", "_get_cache: Unsupported runtime")
    _LOGGERS = ("jax._src.pjit", "jax._src.interpreters.partial_eval",  # jax < 0.10 / >= 0.10
                "jax._src.compiler", "jax._src.compilation_cache")
    """Every module that logs an explanation (a logging filter sees only its own logger's
    records; tests/test_conformance checks this list against the installed JAX)."""

    def __init__(self):
        self.active: Clock | None = None
        self.bucket = "train"
        self._saved_flag: bool | None = None
        jax.monitoring.register_event_duration_secs_listener(self._on_event)
        for name in self._LOGGERS:
            logging.getLogger(name).addFilter(self._on_log)

    def activate(self, clock: "Clock | None") -> None:
        if clock is not None and self._saved_flag is None:
            self._saved_flag = bool(jax.config.jax_explain_cache_misses)
            jax.config.update("jax_explain_cache_misses", True)
        elif clock is None and self._saved_flag is not None:
            jax.config.update("jax_explain_cache_misses", self._saved_flag)
            self._saved_flag = None
        self.active, self.bucket = clock, "train"

    def _on_event(self, event: str, duration: float, **kw):
        clock = self.active
        if clock is None or event not in _COMPILE_EVENTS:
            return
        clock.compile_s[self.bucket] = clock.compile_s.get(self.bucket, 0.0) + duration
        if event == _LOWERING_EVENT:
            clock.compiles[self.bucket] = clock.compiles.get(self.bucket, 0) + 1

    def _on_log(self, record: logging.LogRecord) -> bool:
        """A logging filter: False drops the record (the explanations we asked for)."""
        if self._saved_flag is None:
            return True
        msg = record.getMessage()
        if not msg.startswith(self._DROP):
            return True
        if self.active is not None and self.bucket == "train" and \
                msg.startswith("TRACING CACHE MISS"):
            self.active.note_trace(msg)
        return bool(self._saved_flag)  # the user asked for them: still printed


_NEVER_SEEN = re.compile(r"never seen function:\s*\n\s*(\S+) id=\d+(?: defined at (\S+))?")
_SEEN = re.compile(r"^  for (\S+?)(?: defined at (\S+))?$", re.M)


def _traced_function(msg: str) -> str:
    """'name (file:line)' of the function a TRACING CACHE MISS explanation is about."""
    m = _NEVER_SEEN.search(msg) or _SEEN.search(msg)
    if m is None:
        return "?"
    name, where = m.group(1), m.group(2)
    if where:
        parts = where.split(os.sep)
        where = os.sep.join(parts[-2:])
    return f"{name} ({where})" if where else name


class Clock:
    """Training clock: wall time minus paused time (and minus compile time if not charged)."""

    def __init__(self, charge_compile: bool = True):
        self.charge_compile = charge_compile
        self.compile_s = {"train": 0.0, "eval": 0.0}
        self.compiles = {"train": 0, "eval": 0}
        """Computations compiled (JAX lowerings) while training / while the harness worked."""
        self.interval = 0
        """Reports made so far (the method's RunContext advances it)."""
        self._first_traced: dict[str, int] = {}
        self.retraced: dict[str, dict] = {}
        """Training functions traced again after a report that followed their first trace:
        'name (file:line)' -> {'count': extra traces, 'why': JAX's explanation of the first}."""
        self._start = time.perf_counter()
        self._paused = 0.0
        _meter().activate(self)

    def note_trace(self, explanation: str) -> None:
        fun = _traced_function(explanation)
        first = self._first_traced.setdefault(fun, self.interval)
        if first < self.interval:
            entry = self.retraced.setdefault(fun, {"count": 0, "why": _why(explanation)})
            entry["count"] += 1

    def elapsed(self) -> float:
        t = time.perf_counter() - self._start - self._paused
        return t if self.charge_compile else t - self.compile_s["train"]

    @contextlib.contextmanager
    def paused(self):
        t0 = time.perf_counter()
        meter = _meter()
        meter.bucket = "eval"
        try:
            yield
        finally:
            meter.bucket = "train"
            self._paused += time.perf_counter() - t0

    def close(self):
        meter = _meter()
        if meter.active is self:
            meter.activate(None)


def _why(explanation: str, lines: int = 8) -> str:
    """JAX's explanation without its first line (call site and cost), shortened."""
    body = [ln.strip() for ln in explanation.splitlines()[1:] if ln.strip()]
    return " / ".join(body[:lines])[:600]


_METER: _CompileMeter | None = None


def _meter() -> _CompileMeter:
    """The process's one compile meter (its JAX listeners are registered once), built when
    the first clock starts rather than at import."""
    global _METER
    if _METER is None:
        _METER = _CompileMeter()
    return _METER
