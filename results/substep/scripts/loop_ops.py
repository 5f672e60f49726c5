"""Where an ILD update's XLA operations are: each loop of the compiled update (and of the
forward rollout), how many times it runs and how many operations one pass of its body runs
(session 51).

    python results/substep/scripts/loop_ops.py TASK [--variant task ...] [--batch 32]
        [--out CSV]

`op_count.py` counts the operations an update executes under the profiler; this reads the
same update's optimized HLO (`jit(...).lower(...).compile().as_text()`, no profiler) and
splits that count by loop. For every `while` it prints its part (`forward`, `backward`: the
transpose of the forward, or `rng`: jax's threefry, which CPU lowers as a rolled loop), its
trip count (XLA's `known_trip_count`), the operations in one pass of its body (what the
runtime executes one by one: every instruction but parameters, constants, tuples,
get-tuple-element and bitcasts; a fusion is one, a nested loop one plus its own body) and
how many passes one call makes (trip count times the passes of the loop it sits in; a
small loop's `call` wrapper is followed into). Their sum with the entry computation's own
operations estimates the operations per call, which `op_count.py` measures (session 51,
hopper: the forward's 175,580 both ways, the update's 436,077 estimated and 436,497
measured; tests/test_loop_ops.py checks pointmass's update to 1%).
The forward (`forward`, the benchmark's rollout loss through brax's step as shipped) is
listed first, for the per-substep comparison: with each substep checkpointed, the update's
backward pass over a substep runs the substep forward again plus its VJP, so its body's
operations are at least the forward body's.
"""
from __future__ import annotations

import argparse
import collections
import re

import jax

from bench.report import append_csv
from methods.ild.benchmark import make_rollout_loss, speed_setup
from methods.ild.paired import compiled_chunk, parse_variant
from tasks import make_task

NOT_RUN = {"parameter", "constant", "get-tuple-element", "tuple", "bitcast"}
"""Instructions that the CPU runtime does not execute as operations of their own."""


def computations(hlo: str) -> dict[str, list[str]]:
    """{computation name ('ENTRY' for the entry): its instruction lines} of HLO text."""
    comps, name = {}, None
    for line in hlo.splitlines():
        if line and not line.startswith(" ") and line.rstrip().endswith("{"):
            name = "ENTRY" if line.startswith("ENTRY") else line.split()[0]
            comps[name] = []
        elif name is not None and line.startswith("  "):
            comps[name].append(line)
    return comps


def _opcode(line: str) -> str | None:
    """The opcode of an instruction line: the word before the first '(' that follows its
    result type (which ends in ']', '}' or, for a tuple, ')')."""
    if " = " not in line:
        return None
    m = re.search(r"[\]})] ([a-z][a-z0-9\-_]*)\(", line.split(" = ", 1)[1])
    return m.group(1) if m else None


def loops(hlo: str) -> list[dict]:
    """One row per while loop of `hlo`: its part, trip count, body operations, passes per
    call, nesting depth and jax op name; the entry's own operations as a row 'entry'."""
    comps = computations(hlo)
    run = {c: [ln for ln in lines if (_opcode(ln) or "parameter") not in NOT_RUN]
           for c, lines in comps.items()}
    rows = [{"loop": "entry", "part": "entry", "trip": 1, "body_ops": len(run["ENTRY"]),
             "passes": 1, "depth": 0, "op_name": ""}]

    def visit(comp: str, passes: int, depth: int):
        for line in run[comp]:
            op = _opcode(line)
            if op == "call":  # a small loop's wrapper runs its computation inline
                visit(re.search(r"to_apply=(%[^,\s]+)", line).group(1), passes, depth)
            if op != "while":
                continue
            body = re.search(r"body=(%[^,\s]+)", line).group(1)
            trip = re.search(r'"known_trip_count":\{"n":"(\d+)"', line)
            trip = int(trip.group(1)) if trip else 1
            op_name = (re.search(r'op_name="([^"]*)"', line) or [None, ""])[1]
            part = ("rng" if "threefry" in op_name or "_uniform" in op_name else
                    "backward" if "transpose(" in op_name else "forward")
            rows.append({"loop": body.lstrip("%")[:60], "part": part, "trip": trip,
                         "body_ops": len(run[body]), "passes": passes * trip,
                         "depth": depth + 1, "op_name": op_name[-120:]})
            visit(body, passes * trip, depth + 1)
    visit("ENTRY", 1, 0)
    return rows


def ops_per_call(rows: list[dict]) -> int:
    """The operations one call runs, estimated from `loops`' rows: each body's operations
    times its passes per call, summed."""
    return sum(r["body_ops"] * r["passes"] for r in rows)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("task")
    p.add_argument("--variant", action="append", default=None)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--out")
    a = p.parse_args(argv)
    task = make_task(a.task)
    base = parse_variant("task", a.batch, a.task)
    setup = policy, goals, norm, params, k = speed_setup(task, base)
    init_keys = jax.random.split(k[2], a.batch)
    fwd = jax.jit(make_rollout_loss(task, policy, goals, norm, base))
    texts = {"forward": fwd.lower(params, k[3], init_keys).compile().as_text()}
    for v in a.variant or ["task"]:
        cfg = parse_variant(v, a.batch, a.task)
        chunk, state, one = compiled_chunk(task, cfg, setup)
        texts[f"update {v}"] = chunk.lower(state, one).compile().as_text()
    out = []
    for call, hlo in texts.items():
        rows = loops(hlo)
        total = ops_per_call(rows)
        by_part = collections.Counter()
        for r in rows:
            by_part[r["part"]] += r["body_ops"] * r["passes"]
        print(f"{a.task} {call}: ~{total:,} operations per call ("
              + ", ".join(f"{k_} {v_:,}" for k_, v_ in by_part.most_common()) + ")")
        for r in rows:
            print(f"  {'  ' * r['depth']}{r['part']:8s} trip {r['trip']:4d} x passes "
                  f"{r['passes'] // r['trip']:4d}: {r['body_ops']:5d} ops per pass  "
                  f"{r['op_name'][-70:]}")
        out += [{"task": a.task, "batch": a.batch, "call": call, **r} for r in rows]
    if a.out:
        append_csv(out, a.out)


if __name__ == "__main__":
    main()
