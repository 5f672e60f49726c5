"""Per-task default magnitudes of the transfer column, checked against the expert itself.

`ildbench expert calibrate --task T` measures the deterministic expert and the uniform random
policy (the shared evaluator, REFERENCE_EPISODES fixed episodes: the same numbers the
transfer normalization uses, stored in tasks/data/references) under each generic family on a
magnitude ladder that ends at the family's generic default (bench/perturb.DEFAULTS), from
the smallest magnitude up, and stops at the first magnitude that fails

    kept = (R_expert,m - R_random,0) / (R_expert,0 - R_random,0) >= KEEP   (0.8)
    gap  = (R_expert,m - R_random,m) / (R_expert,0 - R_random,0) >= GAP    (0.5)

The task's default is the generic one where the expert passes there, else the largest
magnitude it passes: the same test dynamics across tasks wherever the expert copes, smaller
only where it does not. `kept` is "the expert itself keeps most of its return" (measured from
the random level, so the reward's sign does not matter); `gap` keeps the normalization
(R - R_random,m) / (R_expert,m - R_random,m) well conditioned (on reacher, observation noise
0.05 makes the expert worse than random, which would flip the sign of every score). A family
is left out of the task's transfer column when even its smallest magnitude fails, or, for the
physics families, when it measurably changes nothing (a fixed random action sequence's
matched states move by less than EFFECT_TOL of their scale at the default). The choice
is written to results/transfer/calibration/<task>.{json,md}; the registry's TaskSpec.transfer
holds it as data (a test checks that they agree).
"""
from __future__ import annotations

import json
import os

from bench.perturb import DEFAULTS, GENERIC, Perturbation, inapplicable
from bench.store import write_json_atomic

KEEP = 0.8
GAP = 0.5
LADDER = {"init_noise": (0.02, 0.05, 0.1),
          "action_noise": (0.05, 0.1, 0.2, 0.3),
          "action_bias": (0.05, 0.1, 0.2),
          "obs_noise": (0.005, 0.01, 0.02, 0.05),
          "actuator": (-0.1, -0.2, -0.3),
          "mass": (0.1, 0.2, 0.3),
          "friction": (-0.25, -0.5)}
assert all(LADDER[f][-1] == DEFAULTS[f] for f in GENERIC)  # the ladder ends at the default
SYSTEM = ("actuator", "mass", "friction")  # families that change the physics parameters
EFFECT_TOL = 1e-2  # reacher mass +30%: 0.0088; its actuator -30%: 0.81; IP mass +30%: 1.18
_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CAL_DIR = os.path.join(_REPO, "results", "transfer", "calibration")


def kept_gap(nominal: tuple[float, float], e: float, r: float) -> tuple[float, float]:
    """(kept, gap) of expert return e and random return r under a perturbation."""
    e0, r0 = nominal
    return (e - r0) / (e0 - r0), (e - r) / (e0 - r0)


def passes(nominal: tuple[float, float], point: tuple[float, float, float],
           keep: float = KEEP, gap: float = GAP) -> bool:
    k, g = kept_gap(nominal, point[1], point[2])
    return k >= keep and g >= gap


def choose(nominal: tuple[float, float], points: list[tuple[float, float, float]],
           keep: float = KEEP, gap: float = GAP) -> tuple[float | None, str]:
    """(default magnitude or None, reason) from nominal (R_expert, R_random) and ladder
    points (magnitude, R_expert, R_random) in ascending |magnitude|."""
    e0, r0 = nominal
    if e0 <= r0:
        raise ValueError(f"the expert ({e0:g}) is not better than random ({r0:g}) on the "
                         "nominal task; retrain the expert before calibrating")
    m_last, e_last, r_last = points[-1]
    if e_last == e0 and r_last == r0:
        return None, (f"no measured effect: expert and random returns at magnitude "
                      f"{m_last:g} equal the nominal ones")
    chosen = None
    for m, e, r in points:
        if not passes(nominal, (m, e, r), keep, gap):
            k, g = kept_gap(nominal, e, r)
            if chosen is None:
                return None, (f"the expert keeps {k:.2f} of its return (gap {g:.2f}) already at "
                              f"the smallest magnitude {m:g} (needs kept >= {keep}, gap >= {gap})")
            return chosen, f"largest magnitude with kept >= {keep} and gap >= {gap}; {m:g} fails"
        chosen = m
    return chosen, f"kept >= {keep} and gap >= {gap} up to the generic default"


def dynamics_effect(task, p: Perturbation, episodes: int = 4, seed: int = 0) -> float:
    """How much family p changes the physics: the largest |difference| of the matched states
    of a fixed uniform-random action sequence rolled out from the same reset, perturbed vs
    nominal, over the largest |nominal matched state| (at least 1)."""
    import jax
    import jax.numpy as jnp

    from bench.perturb import perturbed_task
    from tasks.core import open_loop

    def states(t):
        env = t.env

        def episode(key):
            k_reset, k_act = jax.random.split(key)
            acts = jax.random.uniform(k_act, (t.episode_length, t.action_size), minval=-1,
                                      maxval=1)
            return open_loop(env.step, env.reset(k_reset), acts, t.matched_state)[1]
        return jax.jit(jax.vmap(episode))(jax.random.split(jax.random.PRNGKey(seed), episodes))

    base = states(task)
    pert = states(perturbed_task(task, p))
    return float(jnp.max(jnp.abs(pert - base)) / jnp.maximum(jnp.max(jnp.abs(base)), 1.0))


def calibrate(task_name: str, log=print) -> dict:
    """Measure the ladder (references stored in tasks/data/references), choose, write files."""
    from bench.transfer import references
    from tasks.core import make_task
    from tasks.demo import load_demo

    task = make_task(task_name)
    if task.spec.demo_path is None or task.spec.success_score:
        raise ValueError(f"task {task_name!r} cannot be calibrated: "
                         + ("it has no demo (no expert references) yet; make one with "
                            "`ildbench expert demo`"
                            if task.spec.demo_path is None else
                            "its score is a success rate with fixed references; its test "
                            "dynamics are declared in TaskSpec.transfer"))
    demo = load_demo(task.spec.demo_path, task)
    nominal = (demo.expert_return, demo.random_return)
    # Applicability ignores a declared transfer tuple: calibration is what declares it.
    spec_free = task.__class__(spec=_undeclared(task.spec), env=task.env)
    families = {}
    for fam in GENERIC:
        why = inapplicable(spec_free, Perturbation(fam, LADDER[fam][-1]))
        if why is not None:
            families[fam] = {"default": None, "reason": why, "points": []}
            log(f"[{task_name}] {fam}: skipped ({why})")
            continue
        if fam in SYSTEM:
            effect = dynamics_effect(spec_free, Perturbation(fam, LADDER[fam][-1]))
            if effect < EFFECT_TOL:
                why = (f"no measured effect: at {fam}={LADDER[fam][-1]:g} a fixed random action "
                       f"sequence's matched states move by {effect:.1e} of their scale")
                families[fam] = {"default": None, "reason": why, "points": [],
                                 "effect": effect}
                log(f"[{task_name}] {fam}: skipped ({why})")
                continue
        points = []
        for m in LADDER[fam]:  # up to the first failure: larger magnitudes are not needed
            e, r = references(spec_free, demo, Perturbation(fam, m))
            points.append((m, e, r))
            log(f"[{task_name}] {fam}={m:g}: expert {e:9.2f}  random {r:9.2f}  kept "
                f"{kept_gap(nominal, e, r)[0]:5.2f}")
            if not passes(nominal, (m, e, r)):
                break
        default, reason = choose(nominal, points)
        families[fam] = {"default": default, "reason": reason,
                         "points": [{"magnitude": m, "expert": e, "random": r}
                                    for m, e, r in points]}
    out = {"task": task_name, "demo_sha256": demo.sha256, "keep": KEEP, "gap": GAP,
           "nominal": {"expert": nominal[0], "random": nominal[1]}, "families": families,
           "transfer": [[f, v["default"]] for f, v in families.items()
                        if v["default"] is not None]}
    os.makedirs(CAL_DIR, exist_ok=True)
    write_json_atomic(os.path.join(CAL_DIR, f"{task_name}.json"), out)
    with open(os.path.join(CAL_DIR, f"{task_name}.md"), "w") as f:
        f.write(render(out))
    log(f"[{task_name}] TaskSpec transfer=" + declared_literal(out))
    return out


def _undeclared(spec):
    import dataclasses
    return dataclasses.replace(spec, transfer=None)


def declared_literal(cal: dict) -> str:
    return "(" + ", ".join(f"({f!r}, {m!r})" for f, m in cal["transfer"]) + ",)"


def load(task_name: str) -> dict | None:
    try:
        with open(os.path.join(CAL_DIR, f"{task_name}.json")) as f:
            return json.load(f)
    except FileNotFoundError:
        return None


def render(cal: dict) -> str:
    e0, r0 = cal["nominal"]["expert"], cal["nominal"]["random"]
    lines = [f"# Transfer calibration: {cal['task']}", "",
             f"Expert and random returns under each family's magnitude ladder "
             f"({'`ildbench expert calibrate --task ' + cal['task'] + '`'}; shared evaluator, "
             f"deterministic expert). Nominal: expert {e0:.2f}, random {r0:.2f}. "
             f"kept = (R_expert,m − R_random,0)/(R_expert,0 − R_random,0), gap = "
             f"(R_expert,m − R_random,m)/(R_expert,0 − R_random,0); the default is the largest "
             f"magnitude with kept ≥ {cal['keep']} and gap ≥ {cal['gap']} (and every smaller "
             f"one too), capped at the generic default (the ladder's last magnitude); "
             f"the ladder stops at the first failure.", "",
             "| family | magnitude | R_expert | R_random | kept | gap | default |",
             "|---|---|---|---|---|---|---|"]
    for fam, v in cal["families"].items():
        if not v["points"]:
            lines.append(f"| {fam} | – | – | – | – | – | skipped: {v['reason']} |")
            continue
        for p in v["points"]:
            k, g = kept_gap((e0, r0), p["expert"], p["random"])
            mark = "**default**" if p["magnitude"] == v["default"] else ""
            lines.append(f"| {fam} | {p['magnitude']:g} | {p['expert']:.2f} | "
                         f"{p['random']:.2f} | {k:.2f} | {g:.2f} | {mark} |")
        if v["default"] is None:
            lines.append(f"| {fam} | | | | | | left out: {v['reason']} |")
    lines += ["", f"Registry: `transfer={declared_literal(cal)}`", ""]
    return "\n".join(lines)


def summary_table(task_names) -> str:
    """One markdown row per calibrated task: each family's default, or why it is left out."""
    short = {"no measured effect": "no effect", "no geom pair": "no contacts",
             "the task has no contacts": "no contacts", "normalizes link masses": "no effect",
             "the expert keeps": "expert fails"}
    lines = ["| task | " + " | ".join(GENERIC) + " |", "|---|" + "---|" * len(GENERIC)]
    for name in task_names:
        cal = load(name)
        if cal is None:
            continue
        cells = []
        for fam in GENERIC:
            v = cal["families"][fam]
            if v["default"] is not None:
                cells.append(f"{v['default']:g}" + ("" if v["default"] == DEFAULTS[fam]
                                                    else " ↓"))
            else:
                cells.append("– (" + next((s for k, s in short.items() if k in v["reason"]),
                                          "left out") + ")")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
