"""Changed test dynamics: perturbation families, each with a magnitude knob (0 = nominal).

    init_noise    uniform +/-m added to the initial joint positions and velocities (q, qd)
    action_noise  Gaussian noise of std m added to every action (then clipped to [-1, 1])
    action_bias   a fixed bias m * u, u ~ U(-1, 1)^act drawn once per episode (the paper's
                  cloth test used a fixed bias)
    obs_noise     Gaussian noise of std m added to what the policy observes
    actuator      actuator strength x (1 + m)   (brax: actuator gear; pointmass: force scale)
    mass          body masses x (1 + m)         (brax: link masses; pointmass: the mass)
    friction      contact friction x (1 + m)    (brax: geom friction; tasks without contact
                                                 are unaffected)
    test_noise    the task's own test dynamics at m x their stated size (cloth: the
                  original's uniform +/-0.05 per-step action noise and fixed bias up to
                  +/-0.2, so m = 1 is the paper's test); only tasks that declare it

A task names its own families and default magnitudes in TaskSpec.transfer (cloth:
test_noise = 1 only; the brax tasks: chosen by `ildbench expert calibrate` so that the
expert keeps >= 80% of its return, bench/calibrate.py); otherwise DEFAULTS below apply.

All families but test_noise are one wrapper whose magnitudes (one per family) may be traced:
the evaluator compiles one program per task and policy and passes each perturbation's
magnitudes as an argument (physical parameters are swapped in while a step is traced, as
brax's domain randomization does), instead of compiling one env per variant (measured:
hopper's 5 default families 124 s -> 33 s, inverted_pendulum's 6: 86 s -> 21 s, same
returns to 2e-6 relative). Magnitude 0 is the nominal task itself.

Noise is `fresh` or `fixed` (the noisy families: init_noise, action_noise, action_bias,
obs_noise, test_noise). Fresh: each episode draws its own noise and bias from its own key
(derived from the episode's key), so an evaluation is reproducible and its episodes differ.
Fixed: every episode draws them from one constant key (`FIXED_NOISE_KEY`), the same noise
sequence by step index and the same bias in every training and evaluation episode, of every
seed: the changed dynamics are one deterministic system, as in the paper's cloth protocol
(the original reused one noise sequence and one bias for every iteration and evaluation).

By default a method trains on the nominal task and meets these variants only at test time
(zero-shot transfer). `--train-dynamics FAMILY[:MAGNITUDE][:fixed|fresh]` changes the
dynamics a method trains in (`parse_dynamics`; `physics_scaled` and `with_noise` build its
env): the demo and its references stay nominal, and the run is scored under the same changed
dynamics, beside its nominal score. Normalization under a perturbation uses the expert's and the random policy's returns
measured under the SAME perturbation by the same evaluator (bench/transfer.py).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect

import jax
import jax.numpy as jnp
import numpy as np
import tasks  # noqa: F401  (before brax: tasks/__init__.py keeps brax's import noise quiet)
from brax.envs.base import State, Wrapper

from tasks.core import Task, build_env

FAMILIES = ("init_noise", "action_noise", "action_bias", "obs_noise", "actuator", "mass",
            "friction", "test_noise")
# Default magnitudes (the "transfer" column) and the robustness-curve grid per family.
DEFAULTS = {"init_noise": 0.1, "action_noise": 0.3, "action_bias": 0.2, "obs_noise": 0.05,
            "actuator": -0.3, "mass": 0.3, "friction": -0.5}
GENERIC = FAMILIES[:-1]  # what applies to every task (test_noise only where declared)
NOISY = ("init_noise", "action_noise", "action_bias", "obs_noise", "test_noise")
"""The families that draw noise: fresh per episode, or one fixed sequence (`NOISE_MODES`)."""
NOISE_MODES = ("fresh", "fixed")
FIXED_NOISE_KEY = 1
"""The seed of the one key a `fixed` perturbation draws every episode's noise from (the
original cloth test drew its bias from PRNGKey(1))."""
RANGES = {"init_noise": (0.0, 1.0), "action_noise": (0.0, 2.0), "action_bias": (0.0, 1.0),
          "obs_noise": (0.0, 1.0), "actuator": (-0.9, 3.0), "mass": (-0.9, 3.0),
          "friction": (-0.9, 3.0), "test_noise": (0.0, 4.0)}
"""The magnitudes `--train-dynamics` accepts per family: noise of up to twice the action
range, a bias up to the whole action range (beyond it the [-1, 1] clip saturates), physical
parameters scaled between 0.1x and 4x, the task's own test dynamics up to 4x their size."""
GRID = {"init_noise": (0.0, 0.05, 0.1, 0.2), "action_noise": (0.0, 0.1, 0.3, 0.5),
        "action_bias": (0.0, 0.1, 0.2, 0.4), "obs_noise": (0.0, 0.02, 0.05, 0.1),
        "actuator": (0.0, -0.15, -0.3, -0.5), "mass": (0.0, 0.15, 0.3, 0.6),
        "friction": (0.0, -0.25, -0.5, -0.75), "test_noise": (0.0, 0.5, 1.0, 2.0)}


@dataclasses.dataclass(frozen=True)
class Perturbation:
    family: str
    magnitude: float
    noise: str = "fresh"
    """'fresh' (each episode its own noise) or 'fixed' (one noise sequence and bias for
    every episode); the noisy families only (`NOISY`)."""

    def __post_init__(self):
        if self.noise not in NOISE_MODES:
            raise ValueError(f"unknown noise mode {self.noise!r}; modes: "
                             f"{', '.join(NOISE_MODES)}")
        if self.family in FAMILIES and self.noise == "fixed" and self.family not in NOISY:
            raise ValueError(f"{self.family} draws no noise, so it has no fixed mode; "
                             f"noise modes are for {', '.join(NOISY)}")
        if self.family not in FAMILIES:
            raise ValueError(f"unknown perturbation family {self.family!r}; families: "
                             f"{', '.join(FAMILIES)}")
        if self.family in ("actuator", "mass", "friction") and self.magnitude <= -1:
            raise ValueError(f"{self.family} magnitude must be > -1 (a scale of 1 + m), got "
                             f"{self.magnitude}")
        if self.family in ("init_noise", "action_noise", "obs_noise", "test_noise") and \
                self.magnitude < 0:
            raise ValueError(f"{self.family} magnitude must be >= 0, got {self.magnitude}")

    @property
    def key(self) -> str:
        return f"{self.family}={self.magnitude:g}" + (":fixed" if self.fixed else "")

    @property
    def fixed(self) -> bool:
        return self.noise == "fixed"

    @property
    def physical(self) -> bool:
        """Whether it scales the physics' parameters (actuator, mass, friction)."""
        return self.family in ("actuator", "mass", "friction")

    def describe(self) -> dict:
        """As a record stores it."""
        return {"family": self.family, "magnitude": self.magnitude, "noise": self.noise,
                "key": self.key}


TASK_DEFAULT = "task"
"""`--train-dynamics task`: each task's `TaskSpec.adapt`."""


def parse_dynamics(text: str, task: Task | None = None) -> Perturbation:
    """`FAMILY[:MAGNITUDE][:fixed|fresh]` (e.g. `action_bias:0.2:fixed`, `mass:0.3`,
    `test_noise`) as a Perturbation for the dynamics a method trains in. Without a
    magnitude: the task's default for the family (`TaskSpec.transfer`, else `DEFAULTS`);
    without a mode: fresh. `task`: the task's own adaptation dynamics (`TaskSpec.adapt`), so
    one sweep trains every task in its own. Raises ValueError naming the valid choices for an unknown family
    or mode, a magnitude outside `RANGES` or 0 (the nominal dynamics), or a family that
    cannot change `task`'s dynamics."""
    if str(text).strip() == TASK_DEFAULT:
        adapt = None if task is None else task.spec.adapt
        if adapt is None:
            having = [name for name, spec in tasks.TASKS.items() if spec.adapt is not None]
            raise ValueError(f"--train-dynamics task: task "
                             f"{getattr(task, 'name', None)!r} declares no adaptation dynamics "
                             f"(TaskSpec.adapt); tasks that do: {', '.join(having)}; or name a "
                             "family: FAMILY[:MAGNITUDE][:fixed|fresh]")
        return parse_dynamics(adapt, task)
    parts = [x.strip() for x in str(text).split(":")]
    family, rest = parts[0], parts[1:]
    if family not in FAMILIES:
        raise ValueError(f"--train-dynamics: unknown family {family!r}; families: "
                         f"{', '.join(FAMILIES)} (FAMILY[:MAGNITUDE][:fixed|fresh])")
    noise = "fresh"
    if rest and rest[-1] in NOISE_MODES:
        noise = rest.pop()
    if len(rest) > 1:
        raise ValueError(f"--train-dynamics {text!r}: expected FAMILY[:MAGNITUDE]"
                         f"[:fixed|fresh], e.g. action_bias:0.2:fixed")
    if rest:
        try:
            magnitude = float(rest[0])
        except ValueError:
            raise ValueError(f"--train-dynamics {text!r}: magnitude {rest[0]!r} is not a "
                             f"number (modes: {', '.join(NOISE_MODES)})") from None
    else:
        magnitude = dict(_defaults(task)).get(family, DEFAULTS.get(family, 1.0))
    lo, hi = RANGES[family]
    if not (np.isfinite(magnitude) and lo <= magnitude <= hi) or magnitude == 0:
        raise ValueError(f"--train-dynamics {text!r}: {family} magnitude must be in "
                         f"[{lo:g}, {hi:g}] and not 0 (0 is the nominal dynamics: leave "
                         f"--train-dynamics out), got {magnitude:g}")
    p = Perturbation(family, magnitude, noise)
    if task is not None:
        why = cannot_change(task, p)
        if why is not None:
            usable = [f for f in FAMILIES
                      if cannot_change(task, Perturbation(f, RANGES[f][1])) is None]
            raise ValueError(f"--train-dynamics {text!r}: {family} cannot change the "
                             f"dynamics of task {task.name!r}: {why}; families for this "
                             f"task: {', '.join(usable)}")
    return p


def _obs_of(env, ps, action_size):
    """Recompute a brax env's observation from a pipeline state (signatures differ)."""
    get = env._get_obs
    if len(inspect.signature(get).parameters) >= 2:  # e.g. humanoid's (pipeline_state, action)
        return get(ps, jnp.zeros(action_size))
    return get(ps)


def magnitudes(p: Perturbation) -> np.ndarray:
    """The magnitude vector over FAMILIES with only p's family non-zero."""
    m = np.zeros(len(FAMILIES), np.float32)
    m[FAMILIES.index(p.family)] = p.magnitude
    return m


def _m(mags, family):
    return mags[FAMILIES.index(family)]


def _scaled_attributes(inner, mags) -> dict:
    """{attribute: value} of env `inner`'s physical parameters scaled by (1 + m) for
    actuator, mass and friction (brax: actuator gear, link masses and inertias, geom
    friction; pointmass: its force scale and mass; other tasks: none)."""
    f_act, f_mass, f_fric = (1.0 + _m(mags, f) for f in ("actuator", "mass", "friction"))
    sys = getattr(inner, "sys", None)
    if sys is not None:
        inertia = sys.link.inertia
        scaled = {"sys": sys.replace(
            actuator=sys.actuator.replace(gear=sys.actuator.gear * f_act),
            link=sys.link.replace(inertia=inertia.replace(mass=inertia.mass * f_mass,
                                                          i=inertia.i * f_mass)),
            body_mass=sys.body_mass * f_mass, geom_friction=sys.geom_friction * f_fric)}
    elif hasattr(inner, "force_scale"):  # pointmass: no contact, so no friction
        scaled = {"force_scale": inner.force_scale * f_act, "mass": inner.mass * f_mass}
    else:  # e.g. cloth: its own test_noise
        scaled = {}
    return scaled


@contextlib.contextmanager
def _scaled_physics(inner, mags):
    """The env's physical parameters scaled (`_scaled_attributes`) while a step or reset is
    traced (brax's own domain randomization swaps `sys` the same way), so the magnitudes are
    traced values: one compilation serves every magnitude."""
    scaled = _scaled_attributes(inner, mags)
    saved = {name: getattr(inner, name) for name in scaled}
    for name, value in scaled.items():
        setattr(inner, name, value)
    try:
        yield
    finally:
        for name, value in saved.items():
            setattr(inner, name, value)


class _Perturbed(Wrapper):
    """The env under magnitudes `mags` (one per family, see `magnitudes`). The magnitudes
    may be traced: the evaluator compiles one program per task (the `template`) and passes
    each perturbation's vector as an argument, instead of compiling an env per variant.
    `fixed`: every episode draws its noise from `FIXED_NOISE_KEY` (the env's own test noise
    too, through its `noise_info`), not from its reset key. `physics` False: the physical
    parameters are left as they are (a training env has them scaled in already,
    `physics_scaled`)."""

    def __init__(self, env, mags, fixed: bool = False, physics: bool = True):
        super().__init__(env)
        self.mags = mags
        self.fixed = fixed
        self.physics = physics

    @property
    def template(self) -> "_Perturbed":
        """The magnitude-free env the evaluator caches its compiled episodes on."""
        return _template(self.env, self.fixed, self.physics)

    def bind(self, mags) -> "_Perturbed":
        return _Perturbed(self.env, mags, self.fixed, self.physics)

    def _physics(self):
        if not self.physics:
            return contextlib.nullcontext()
        return _scaled_physics(self.env.unwrapped, jnp.asarray(self.mags))

    def reset(self, rng):
        mags = jnp.asarray(self.mags)
        with self._physics():
            s = self.env.reset(rng)  # the nominal reset: magnitude 0 reproduces it exactly
            source = jax.random.PRNGKey(FIXED_NOISE_KEY) if self.fixed else rng
            noise_info = getattr(self.env.unwrapped, "noise_info", None)
            if self.fixed and noise_info is not None:  # the env's own test noise (cloth)
                s = s.replace(info={**s.info, **noise_info(source)})
            k_init, k_bias, k_step = jax.random.split(jax.random.fold_in(source, 0x9E27), 3)
            m_init = _m(mags, "init_noise")
            noisy = self._init_noise(s, k_init, m_init)
            s = jax.tree.map(lambda a, b: jnp.where(m_init != 0, a, b), noisy, s)
        bias = _m(mags, "action_bias") * jax.random.uniform(
            k_bias, (self.env.action_size,), minval=-1, maxval=1)
        s = s.replace(info={**s.info, "perturb_key": k_step, "perturb_bias": bias})
        return self._observe(s)

    def _init_noise(self, s: State, key, m):
        inner = self.env.unwrapped
        ps = s.pipeline_state
        if isinstance(ps, jax.Array):  # pure-JAX tasks: the pipeline state is the vector
            ps = ps + jax.random.uniform(key, ps.shape, minval=-m, maxval=m)
            return s.replace(pipeline_state=ps, obs=ps)
        if not hasattr(inner, "pipeline_init"):  # e.g. cloth: init_noise cannot change it
            return s
        k_q, k_qd = jax.random.split(key)
        q = ps.q + jax.random.uniform(k_q, ps.q.shape, minval=-m, maxval=m)
        qd = ps.qd + jax.random.uniform(k_qd, ps.qd.shape, minval=-m, maxval=m)
        ps = inner.pipeline_init(q, qd)
        return s.replace(pipeline_state=ps, obs=_obs_of(inner, ps, inner.action_size))

    def _observe(self, s: State) -> State:
        m = _m(jnp.asarray(self.mags), "obs_noise")
        key, k = jax.random.split(s.info["perturb_key"])
        noisy = s.obs + m * jax.random.normal(k, s.obs.shape)
        # The key advances only under observation noise, so every other family draws the
        # same noise stream as when each variant was its own env.
        key = jnp.where(m != 0, key, s.info["perturb_key"])
        return s.replace(obs=jnp.where(m != 0, noisy, s.obs),
                         info={**s.info, "perturb_key": key})

    def step(self, s: State, action):
        key, k = jax.random.split(s.info["perturb_key"])
        action = action + _m(jnp.asarray(self.mags), "action_noise") * jax.random.normal(
            k, action.shape)
        action = jnp.clip(action + s.info["perturb_bias"], -1.0, 1.0)
        with self._physics():
            s2 = self.env.step(s, action)
        s2 = s2.replace(info={**s2.info, "perturb_key": key,
                              "perturb_bias": s.info["perturb_bias"]})
        return self._observe(s2)


def _has_joint_coordinates(inner) -> bool:
    """Whether init_noise can perturb env `inner`'s initial state: a brax pipeline (q, qd)
    or a pure-JAX task whose pipeline state is the state vector."""
    return hasattr(inner, "pipeline_init") or isinstance(
        jax.eval_shape(inner.reset, jax.random.PRNGKey(0)).pipeline_state,
        jax.ShapeDtypeStruct)


@functools.lru_cache(maxsize=64)
def _template(env, fixed: bool = False, physics: bool = True) -> _Perturbed:
    return _Perturbed(env, np.zeros(len(FAMILIES), np.float32), fixed, physics)


def inapplicable(task: Task, p: Perturbation) -> str | None:
    """Why family p cannot change this task's dynamics (None if it can). Such families are
    skipped, recorded with the reason, and left out of the transfer score. Magnitude 0 is
    the nominal task, always applicable."""
    if p.magnitude == 0:
        return None
    declared = task.spec.transfer
    if declared is not None and p.family not in dict(declared):
        return (f"task {task.name!r} declares its test dynamics as "
                f"{', '.join(f for f, _ in declared)} (TaskSpec.transfer)")
    return cannot_change(task, p)


def cannot_change(task: Task, p: Perturbation) -> str | None:
    """Why family p has no effect on this task's dynamics (None if it has): the physical
    reasons of `inapplicable`, without its rule that a task's declared test families are
    the only ones scored (training dynamics may use any family that changes the task)."""
    inner = task.env.unwrapped
    if p.family == "test_noise" and "test_noise" not in dict(task.spec.transfer or ()):
        return f"task {task.name!r} declares no test_noise dynamics"
    if p.physical and p.magnitude != 0 and not _scaled_attributes(
            inner, magnitudes(Perturbation(p.family, 0.5))):
        return f"task {task.name!r} has no physical parameters that {p.family} scales"
    if p.family == "init_noise" and not _has_joint_coordinates(inner):
        return f"task {task.name!r} has no joint coordinates for init_noise to perturb"
    sys = getattr(inner, "sys", None)
    if p.family == "friction":
        if sys is None:
            return "the task has no contacts"
        ct = np.asarray(sys.geom_contype)
        ca = np.asarray(sys.geom_conaffinity)
        if not (np.bitwise_and(ct[:, None], ca[None, :]) != 0).any():
            return "no geom pair can collide (contype/conaffinity), so no contact friction"
    if p.family == "mass" and sys is not None and task.spec.backend in ("spring",
                                                                         "positional"):
        if float(sys.spring_mass_scale) == 1.0:
            return (f"brax's {task.spec.backend} pipeline normalizes link masses for this task "
                    "(spring_mass_scale = 1): mass has no effect")
    return None


@functools.lru_cache(maxsize=256)
def perturbed_task(task: Task, p: Perturbation) -> Task:
    """The task with perturbed test dynamics. Every family but test_noise wraps the task's
    own env (one template per task: the evaluator compiles once for all of them); test_noise
    builds the task's declared noisy env (cloth)."""
    if p.magnitude == 0:  # the nominal task itself: exactly the nominal score
        return task
    if p.family == "test_noise":
        return Task(spec=task.spec, env=_Perturbed(build_env(task.spec, test_noise=p.magnitude),
                                                   np.zeros(len(FAMILIES), np.float32),
                                                   p.fixed))
    return Task(spec=task.spec, env=_Perturbed(task.env, magnitudes(p), p.fixed))


def physics_scaled(task: Task, p: Perturbation) -> Task:
    """A fresh copy of `task` whose parameters carry p's changed physics as constants: the
    physical families scale its parameters in place of the evaluator's traced swap (the
    same numbers), so a physics plan applied to the copy afterwards (whose rewrites read the
    parameters once, when they are built) steps the changed physics; test_noise builds the
    task's declared noisy env. The other families: `task` itself (their noise is a wrapper,
    `with_noise`). The registry's cached task is left as it is."""
    if p.family == "test_noise":
        return Task(spec=task.spec, env=build_env(task.spec, test_noise=p.magnitude))
    if not p.physical:
        return task
    env = build_env(task.spec)
    inner, given = env.unwrapped, task.env.unwrapped
    if hasattr(given, "sys"):  # a copy (e.g. without joint limits) keeps its own sys
        inner.sys = given.sys
    for name, value in _scaled_attributes(inner, magnitudes(p)).items():
        setattr(inner, name, value)
    return Task(spec=task.spec, env=env)


def with_noise(env, p: Perturbation):
    """`env` (a training env, its physics already changed by `physics_scaled`) with p's
    noise: the same wrapper the evaluator scores under, its physical parameters left alone.
    A physical family: `env` itself."""
    if p.physical:
        return env
    mags = np.zeros(len(FAMILIES), np.float32) if p.family == "test_noise" else magnitudes(p)
    return _Perturbed(env, mags, p.fixed, physics=False)


def _defaults(task: Task | None) -> tuple[tuple[str, float], ...]:
    """(family, default magnitude) pairs: the task's declared ones, else every generic
    family at DEFAULTS."""
    declared = None if task is None else task.spec.transfer
    return declared if declared is not None else tuple((f, DEFAULTS[f]) for f in GENERIC)


def default_set(task: Task | None = None) -> list[Perturbation]:
    """The transfer column's perturbations."""
    return [Perturbation(f, m) for f, m in _defaults(task)]


def grid_set(task: Task | None = None) -> list[Perturbation]:
    """The robustness-curve grid over the task's families."""
    return [Perturbation(f, m) for f, d in _defaults(task) for m in sorted(
        set(GRID[f]) | {d}, key=abs)]
