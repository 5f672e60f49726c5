"""The task registry: one literal table of frozen specs.

Every task runs 128-step episodes. The physics backend is pinned per task (brax's own
default differs per class, so it is never left implicit); the measured forward and gradient
env-steps/s that chose it are in results/speed/backends.csv (`python -m benchmarks.backends`).

The *matched state* is the vector imitation losses compare. For Brax tasks it is, per body,
[pos (3), rot (4, quaternion wxyz), vel (3), ang (3)] taken from the pipeline state's world
frame (x, xd), laid out field by field over bodies: [pos(nb*3), rot(nb*4), vel(nb*3),
ang(nb*3)], i.e. 13 * num_bodies numbers, as the paper's code did with brax v1's QP.
"""
from __future__ import annotations

import dataclasses
import os
from typing import Any, Mapping

DATA_DIR = os.path.join(os.path.dirname(__file__), "data")
EPISODE_LENGTH = 128

_BRAX_MATCHED = "per body: pos, rot (quat), vel, ang from the pipeline state (13 x bodies)"


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """A benchmark task. Frozen: a change is a one-line diff of the table below."""

    name: str
    """Harness id."""
    env: str
    """'brax:<name>' for brax.envs, or 'ildbench:<name>' for a task implemented in tasks/."""
    backend: str
    """Physics pipeline, pinned ('generalized' | 'positional' | 'spring' | 'analytic')."""
    observation: str
    """What the policy sees (documentation)."""
    matched_state: str
    """What imitation losses compare (documentation; the code is Task.matched_state)."""
    demo: str | None = None
    """Demo file name inside tasks/data/, or None until an expert exists."""
    episode_length: int = EPISODE_LENGTH
    env_kwargs: tuple[tuple[str, Any], ...] = ()
    """Extra constructor arguments for the environment, as (key, value) pairs."""
    paper_expert_return: float | None = None
    """The paper's expert row (Table 2), for the ours-vs-paper expert table (docs/tasks.md)."""
    transfer: tuple[tuple[str, float], ...] | None = None
    """The test dynamics of the transfer column as (family, default magnitude) pairs
    (bench/perturb.py); for the brax tasks copied from `ildbench expert calibrate` (the expert
    keeps >= 80% of its return; results/transfer/calibration). None: every generic family
    at its generic default (tasks not calibrated yet)."""
    adapt: str | None = None
    """The changed dynamics of the adaptation table (`--train-dynamics task`, docs/protocol.md):
    one of the task's transfer families, at its calibrated magnitude, so that a method trained
    in it is scored in the same dynamics as the zero-shot transfer column. A physical family
    where the task has one (weaker actuators: a policy must push harder than the demo did),
    else a fresh action bias. None: the task has no adaptation cell."""
    success_score: bool = False
    """The return is a success indicator (0/1): the normalized score is the success rate,
    with references 1 and 0 under every test dynamics (not re-measured per perturbation)."""
    weak_reference: str | None = None
    """Why the expert reference does not make this task's normalized score comparable with
    the others' (measured): such a task keeps its leaderboard rows but is left out of the
    cross-task aggregates, with this reason printed beside them. None: a sound reference."""

    @property
    def demo_path(self) -> str | None:
        return None if self.demo is None else os.path.join(DATA_DIR, self.demo)

    def kwargs(self) -> Mapping[str, Any]:
        return dict(self.env_kwargs)


# fmt: off
_TABLE: tuple[TaskSpec, ...] = (
    TaskSpec("pointmass", "ildbench:pointmass", "analytic",
             "x, v (2)", "x, v (2)", demo="pointmass.npz"),
    TaskSpec("inverted_pendulum", "brax:inverted_pendulum", "positional",
             "q, qd (4)", _BRAX_MATCHED, demo="inverted_pendulum.npz", paper_expert_return=128.0,
             adapt="actuator",
             transfer=(("init_noise", 0.1), ("action_noise", 0.3), ("action_bias", 0.2),
                       ("obs_noise", 0.05), ("actuator", -0.3), ("mass", 0.3))),
    TaskSpec("reacher", "brax:reacher", "positional",
             "brax reacher obs (11)", _BRAX_MATCHED, demo="reacher.npz", paper_expert_return=-22.5,
             adapt="actuator",
             transfer=(("init_noise", 0.1), ("action_noise", 0.2), ("action_bias", 0.2),
                       ("actuator", -0.3))),
    TaskSpec("acrobot", "ildbench:acrobot", "generalized",
             "theta1, theta2, dtheta1, dtheta2 (4)", _BRAX_MATCHED, demo="acrobot.npz",
             paper_expert_return=200.8,
             adapt="action_bias",
             transfer=(("init_noise", 0.1), ("action_noise", 0.1), ("action_bias", 0.2),
                       ("obs_noise", 0.05))),
    TaskSpec("swimmer", "brax:swimmer", "generalized",
             "brax swimmer obs (8)", _BRAX_MATCHED, demo="swimmer.npz", paper_expert_return=4.3,
             adapt="actuator",
             transfer=(("init_noise", 0.1), ("action_noise", 0.1), ("obs_noise", 0.05),
                       ("actuator", -0.2), ("mass", 0.3))),
    TaskSpec("hopper", "brax:hopper", "spring",
             "brax hopper obs (11)", _BRAX_MATCHED, demo="hopper.npz", paper_expert_return=293.0,
             adapt="actuator",
             transfer=(("action_noise", 0.2), ("action_bias", 0.1), ("obs_noise", 0.02),
                       ("actuator", -0.3), ("friction", -0.5))),
    TaskSpec("walker2d", "brax:walker2d", "spring",
             "brax walker2d obs (17)", _BRAX_MATCHED, demo="walker2d.npz",
             paper_expert_return=289.0,
             adapt="actuator",
             transfer=(("init_noise", 0.05), ("action_noise", 0.3), ("action_bias", 0.2),
                       ("obs_noise", 0.05), ("actuator", -0.3), ("mass", 0.3),
                       ("friction", -0.5))),
    TaskSpec("ant", "brax:ant", "spring",
             "brax ant obs (27)", _BRAX_MATCHED, demo="ant.npz", paper_expert_return=624.0,
             adapt="actuator",
             transfer=(("init_noise", 0.1), ("action_noise", 0.1), ("action_bias", 0.1),
                       ("obs_noise", 0.02), ("actuator", -0.1), ("friction", -0.25))),
    TaskSpec("humanoid", "brax:humanoid", "spring",
             "brax humanoid obs (244)", _BRAX_MATCHED, demo="humanoid.npz", paper_expert_return=933.0,
             adapt="actuator",
             transfer=(("action_noise", 0.3), ("action_bias", 0.2), ("actuator", -0.1),
                       ("friction", -0.25))),
    TaskSpec("cloth", "ildbench:cloth", "cloth",
             "= matched state (1736)",
             "per particle (x, y, z, vx, vy, vz) x 288, then gripper 0 and 1 (x, y, z, r)",
             demo="cloth.npz", episode_length=80, adapt="test_noise:fixed",
             transfer=(("test_noise", 1.0),),
             success_score=True),
)
# fmt: on

TASKS: dict[str, TaskSpec] = {}


class UnknownTaskError(KeyError):
    def __str__(self) -> str:  # KeyError quotes its message; we want it plain
        return str(self.args[0])


def register(spec: TaskSpec) -> TaskSpec:
    """Add a task. Re-registering a name raises (brax silently overwrote; we do not)."""
    if spec.name in TASKS:
        raise ValueError(f"task {spec.name!r} is already registered; pick another name")
    TASKS[spec.name] = spec
    return spec


def get_spec(name: str) -> TaskSpec:
    try:
        return TASKS[name]
    except KeyError:
        raise UnknownTaskError(
            f"unknown task {name!r}; valid tasks: {', '.join(sorted(TASKS))}") from None


for _spec in _TABLE:
    register(_spec)
