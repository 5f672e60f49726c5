"""How much faster could ILD's `hand_adjoint` update get from a hand-written VJP of one more
piece of brax's spring substep? An upper bound per piece (session 49).

    python results/substep/scripts/free_piece_bound.py TASK [--pieces none,impulse,...]
        [--rounds 6] [--repeats 8] [--batch 32] [--out CSV]

For each piece, ILD's update as TASK trains with `hand_adjoint` (`task,hand_adjoint`, as
`methods.ild.paired` names it) is built with that piece's output passed through
`jax.lax.stop_gradient`: its backward is free, and so is any backward upstream that only it
needed. That update's gradient is wrong, so it is only timed: its speed-up over `none` (the
update as it is) bounds what any hand-written VJP of the piece could gain, since a
hand-written VJP still costs something. Pieces (the functions `tasks.spring_adjoint.step`
still differentiates by XLA's reverse mode):
- impulse: each contact's impulse (`_impulse`, brax's closure, copied);
- contact: the contacts (`brax.contact.get`, MJX's collision);
- joint_types: the joints' per-type constraint forces (brax's `_free`, `_one_dof`,
  `_two_dof`, `_three_dof` through `scan.link_types`, in `joints_resolve`);
- to_tau: the actuator forces (`brax.actuator.to_tau`);
- inverse: the joint coordinates q, qd (`brax.kinematics.inverse`; the last substep only,
  the others being lean);
- axis_angle: `brax.kinematics.axis_angle_ang`, the Euler angles both the joints' forces and
  `kinematics.inverse` compute (patched in brax's module while the update traces);
- all: every one of the above.
The variants are compiled one after another (the patch is in place only while one traces
and compiles), then timed round by round, interleaved in one process as
`methods.ild.paired` does: `--repeats` updates each per round; the first round is a
warm-up and is not kept. Prints the median seconds per update and the median (range) over
rounds of the speed-up over `none`; `--out` appends one row per variant and round.
"""
from __future__ import annotations

import argparse
import contextlib
import statistics
import time
import types

import brax.kinematics
import jax
from brax import actuator, contact, kinematics, scan

import tasks.spring_adjoint as sa
from bench.malloc import reexec_with_hugepages
from bench.report import append_csv
from bench.runner import speed_settings
from methods.ild.benchmark import speed_setup
from methods.ild.paired import compiled_chunk, parse_variant
from tasks import make_task

PIECES = ("none", "impulse", "contact", "joint_types", "to_tau", "inverse", "axis_angle",
          "all")
_sg = jax.lax.stop_gradient
_axis_angle_ang = brax.kinematics.axis_angle_ang


def _free(fn):
    return lambda *a: _sg(fn(*a))


def _module_with(module, name: str):
    """A stand-in for `module` whose function `name` has a free backward; everything else is
    the module's own (tasks.spring_adjoint also calls, e.g., kinematics.link_to_joint_frame)."""
    return types.SimpleNamespace(**{**vars(module), name: _free(getattr(module, name))})


def _module_patches(piece: str) -> dict:
    """{name in tasks.spring_adjoint: stand-in} for `piece`."""
    on = lambda name: piece in (name, "all")  # noqa: E731
    p = {}
    if on("impulse"):
        p["_impulse"] = _free(sa._impulse)
    if on("contact"):
        p["contact"] = _module_with(contact, "get")
    if on("joint_types"):
        p["scan"] = _module_with(scan, "link_types")
    if on("to_tau"):
        p["actuator"] = _module_with(actuator, "to_tau")
    if on("inverse"):
        p["kinematics"] = _module_with(kinematics, "inverse")
    return p


@contextlib.contextmanager
def free_backward(piece: str):
    """`piece`'s backward made free in `tasks.spring_adjoint.step` while the block runs."""
    if piece in ("axis_angle", "all"):  # first: the stand-ins below copy the module
        brax.kinematics.axis_angle_ang = _free(_axis_angle_ang)
    patches = _module_patches(piece)
    old = {name: getattr(sa, name) for name in patches}
    for name, fn in patches.items():
        setattr(sa, name, fn)
    try:
        yield
    finally:
        for name, fn in old.items():
            setattr(sa, name, fn)
        brax.kinematics.axis_angle_ang = _axis_angle_ang


def run(task_name: str, pieces: list[str], batch: int, rounds: int, repeats: int):
    cfg = parse_variant("task,hand_adjoint", batch, task_name)
    task = make_task(task_name)
    setup = speed_setup(task, cfg)
    calls = -(-repeats // cfg.chunk)
    timed = {}
    for piece in pieces:
        with free_backward(piece):  # traced and compiled with the patch in place
            timed[piece] = compiled_chunk(task, cfg, setup)
    seconds = {piece: [] for piece in pieces}
    for r in range(rounds + 1):
        for piece, (chunk, state, n) in timed.items():
            t0 = time.perf_counter()
            for _ in range(calls):
                state = chunk(state, n)[0]
            jax.block_until_ready(state)
            if r:  # round 0 warms up
                seconds[piece].append((time.perf_counter() - t0) / (calls * cfg.chunk))
    base, settings, rows = seconds[pieces[0]], speed_settings(), []
    for piece in pieces:
        up = [b / s for b, s in zip(base, seconds[piece])]
        print(f"{task_name} {piece}: {statistics.median(seconds[piece]):.4f} s/update, "
              f"over {pieces[0]} {statistics.median(up):.3f}x [{min(up):.3f}, {max(up):.3f}]",
              flush=True)
        rows += [{"task": task_name, "batch": batch, "variant": "task,hand_adjoint",
                  "free_backward": piece, "round": r, "seconds": float(f"{s:.4g}"),
                  f"over_{pieces[0]}": round(u, 3), **settings}
                 for r, (s, u) in enumerate(zip(seconds[piece], up))]
    return rows


def main(argv=None):
    reexec_with_hugepages()  # as the benchmark and `ildbench` run (bench.malloc)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("task")
    p.add_argument("--pieces", default=",".join(PIECES),
                   help=f"comma-separated, the first the baseline; of {', '.join(PIECES)}")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--repeats", type=int, default=8)
    p.add_argument("--out")
    a = p.parse_args(argv)
    pieces = a.pieces.split(",")
    unknown = [x for x in pieces if x not in PIECES]
    if unknown:
        p.error(f"unknown piece(s) {unknown}; pick from {', '.join(PIECES)}")
    rows = run(a.task, pieces, a.batch, a.rounds, a.repeats)
    if a.out:
        append_csv(rows, a.out)


if __name__ == "__main__":
    main()
