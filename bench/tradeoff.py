"""Speed-accuracy trade-offs ("users trade speed for accuracy: measure that trade").

    ildbench tradeoff backends --task hopper    env-steps/s (forward and gradient) of each
                                                physics backend beside its trajectory error
                                                against the most accurate one (generalized)
                                                on the same actions from the same states
    ildbench tradeoff budget --store S --task T score reached vs training budget (1, 2, 5, 10
                                                min), read off the anytime curves of runs
                                                whose budget covers it
    ildbench tradeoff ild --task T --budget 3m  ILD's truncation length x batch size grid:
                                                final score, updates done, env-steps/s
    ildbench tradeoff utd --task T --budget 3m  DAC's and PWIL's update-to-data ratio (1, 0.5,
                                                0.25): final score, env steps and updates
                                                each run made, beside the ratio-1 row
    ildbench tradeoff substeps --task cloth     the cloth's substeps per action (dt =
                                                0.1 s / substeps): stable or not, trajectory
                                                error of the expert's replay against 200
                                                substeps, success, forward and gradient
                                                env-steps/s

Every part writes results/tradeoff/<task>_<part>.csv/.md and a PNG.

Budget part: a run's anytime score at t is the score of the policy it held at t. Where a
learning-rate schedule runs over a fixed number of updates/epochs, a run stopped by a budget
t is the same run as a longer one read at t. A schedule over the budget itself (ILD's
default `lr_schedule='budget'`) makes a different run for each budget: such runs are read at
their own budget only.
"""
from __future__ import annotations

import os
import time

import matplotlib

matplotlib.use("Agg")
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from bench import curves  # noqa: E402
from bench.plots import save_figure  # noqa: E402
from bench.report import write_table  # noqa: E402
from bench.store import Store  # noqa: E402
from tasks import TASKS, get_spec, make_task  # noqa: E402
from tasks.core import Task, open_loop, task_with_backend  # noqa: E402

BACKENDS = ("generalized", "positional", "spring")
REFERENCE_BACKEND = "generalized"
BUDGET_MINUTES = (1, 2, 5, 10)
_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(_REPO, "results", "tradeoff")


def probe_actions(name: str, batch: int, horizon: int) -> tuple[jax.Array, jax.Array]:
    """(actions (B, H, act), reset keys (B, 2)): the demo's own actions and initial states
    where a demo exists, else smooth random actions (sinusoids of random phase, amplitude
    0.5) from fixed keys."""
    spec = get_spec(name)
    if spec.demo_path and os.path.exists(spec.demo_path):
        with np.load(spec.demo_path) as z:
            acts, keys = z["actions"][:batch, :horizon], z["init_keys"][:batch]
        return jnp.asarray(acts), jnp.asarray(keys, jnp.uint32)
    act = make_task(name).action_size
    k1, k2 = jax.random.split(jax.random.PRNGKey(7))
    phase = jax.random.uniform(k1, (batch, 1, act), maxval=2 * np.pi)
    freq = jax.random.uniform(k2, (batch, 1, act), minval=0.05, maxval=0.3)
    t = jnp.arange(horizon)[None, :, None]
    return 0.5 * jnp.sin(freq * t + phase), jax.random.split(jax.random.PRNGKey(8), batch)


def open_loop_positions(task: Task, actions, keys) -> np.ndarray:
    """(B, H+1, bodies, 3) world positions of every body under open-loop actions."""
    nb = task.state_size // 13

    def one(acts, key):
        s = task.env.reset(key)
        pos = open_loop(task.env.step, s, acts, lambda s: task.matched_state(s)[:3 * nb])[1]
        return jnp.concatenate([task.matched_state(s)[None, :3 * nb], pos])
    pos = jax.jit(jax.vmap(one))(actions, keys)
    return np.asarray(pos).reshape(actions.shape[0], actions.shape[1] + 1, nb, 3)


def _rollout_fn(task: Task, horizon: int):
    env = task.env

    def rollout(actions, key):  # actions (H, act)
        return open_loop(env.step, env.reset(key), actions, task.matched_state)[1]

    return rollout


def measure(task: Task, batch: int, horizon: int, repeats: int = 3,
            action_scale: float = 0.3) -> dict:
    rollout = _rollout_fn(task, horizon)
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    # Moderate random actions: at full scale some tasks (inverted_pendulum) drive the state
    # itself to NaN within 128 steps, which would time NaN arithmetic, not physics.
    actions = action_scale * jax.random.uniform(
        jax.random.PRNGKey(1), (batch, horizon, task.action_size), minval=-1, maxval=1)
    fwd = jax.jit(jax.vmap(rollout))
    loss = lambda a: jnp.mean(jax.vmap(rollout)(a, keys) ** 2)
    grad = jax.jit(jax.grad(loss))

    def timed(f, *args):
        t0 = time.perf_counter()
        compiled = f.lower(*args).compile()
        c = time.perf_counter() - t0
        jax.block_until_ready(compiled(*args))  # warm-up
        t0 = time.perf_counter()
        for _ in range(repeats):
            out = jax.block_until_ready(compiled(*args))
        return out, c, (time.perf_counter() - t0) / repeats

    _, fwd_c, fwd_t = timed(fwd, actions, keys)
    g, grad_c, grad_t = timed(grad, actions)
    steps = batch * horizon
    return dict(fwd_steps_per_s=round(steps / fwd_t, 1), grad_steps_per_s=round(steps / grad_t, 1),
                grad_over_fwd=round(grad_t / fwd_t, 2), fwd_compile_s=round(fwd_c, 1),
                grad_compile_s=round(grad_c, 1),
                grad_finite=bool(np.isfinite(np.asarray(g)).all()), error="")


def backends(name: str, batch: int = 16, horizon: int = 128, repeats: int = 3,
             log=print) -> pd.DataFrame:
    actions, keys = probe_actions(name, batch, horizon)
    ref_pos = None
    rows = []
    for backend in (REFERENCE_BACKEND,) + tuple(b for b in BACKENDS if b != REFERENCE_BACKEND):
        row = {"task": name, "backend": backend, "registry_default": get_spec(name).backend
               == backend}
        try:
            task = task_with_backend(name, backend)
            pos = open_loop_positions(task, actions, keys)
            if ref_pos is None:
                ref_pos = pos
            err = np.linalg.norm(pos - ref_pos, axis=-1).mean(axis=(0, 2))  # (H+1,) metres
            row.update({"pos_err_step10_m": float(err[min(10, horizon)]),
                        "pos_err_mean_m": float(err.mean()),
                        "pos_err_final_m": float(err[-1]),
                        "finite": bool(np.isfinite(pos).all())})
            row.update(measure(task, batch, horizon, repeats))
        except Exception as e:  # an unsupported backend is a row, not a crash
            row["error"] = f"{type(e).__name__}: {e}"[:200]
        log(str(row))
        rows.append(row)
    return pd.DataFrame(rows)


CLOTH_SUBSTEPS = (34, 42, 50, 75, 100, 200)


def cloth_substeps(substeps=CLOTH_SUBSTEPS, batch: int = 10, repeats: int = 2,
                   gradient: bool = True, log=print) -> pd.DataFrame:
    """The cloth's integrator trade: fewer substeps (larger dt) are faster until dt crosses
    the explicit stability limit. Error = mean particle distance over the 80 steps of the
    expert's replay against the finest setting."""
    import time

    from tasks.cloth import sim
    from tasks.cloth.env import ClothHang, expert_actions
    acts = jnp.asarray(expert_actions())
    finest = max(substeps)
    limit = sim.stability_limit()
    traj, rows = {}, []
    for n in sorted(substeps, reverse=True):
        env = ClothHang(dt=0.1 / n, substeps=n, check_stability=False)

        def replay(a, env=env):
            return open_loop(env.step, env.reset(jax.random.PRNGKey(0)), a,
                             lambda s: (s.pipeline_state["x"], s.reward))[1]

        def batch_loss(a, env=env):
            s = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))
            s = open_loop(lambda s, a: jax.vmap(env.step)(s, jnp.broadcast_to(a, (batch, 8))),
                          s, a)[0]
            return jnp.mean(s.obs ** 2)

        x, rew = (np.asarray(v) for v in jax.jit(replay)(acts))
        traj[n] = x
        row = {"substeps": n, "dt_s": 0.1 / n, "stable": 0.1 / n < limit,
               "max_strain": float(max(jax.vmap(sim.max_strain)(jnp.asarray(x)))),
               "expert_success": float(rew[-1])}
        fns = [("fwd", jax.jit(batch_loss))]
        if gradient:
            fns.append(("grad", jax.jit(jax.grad(batch_loss))))
        for label, fn in fns:
            jax.block_until_ready(fn(acts))
            t0 = time.perf_counter()
            for _ in range(repeats):
                jax.block_until_ready(fn(acts))
            row[f"{label}_steps_per_s"] = batch * 80 * repeats / (time.perf_counter() - t0)
        err = np.linalg.norm(x - traj[finest], axis=-1)
        row.update({"err_mean_mm": 1e3 * float(err.mean()), "err_max_mm": 1e3 * float(err.max())})
        log(str(row))
        rows.append(row)
    return pd.DataFrame(rows).sort_values("substeps").reset_index(drop=True)


def budget_table(store: Store, task: str, minutes=BUDGET_MINUTES,
                 more_stores: tuple = ()) -> pd.DataFrame:
    """Per method and variant (the leaderboard's: runs pool only under equal version, preset,
    config and evaluation), the mean anytime score at each budget over the runs whose
    budget reaches it. `method` carries the variant id where a method has several.
    `more_stores` adds their runs (e.g. budget-scheduled runs at shorter budgets, kept out of
    the leaderboard's store)."""
    from bench.leaderboard import variant
    rows = []
    for r in [r for s in (store, *more_stores) for r in s.records()]:
        if r["task"] != task or r.get("status") not in ("ok", "diverged"):
            continue
        secs = (r.get("budget") or {}).get("seconds")
        if not secs:
            continue
        own_budget_only = (r.get("config") or {}).get("lr_schedule") == "budget"
        for m in minutes:
            if own_budget_only and abs(secs - 60 * m) >= 1e-6:
                continue
            if secs + 1e-6 >= 60 * m:
                # At the run's own budget: its final score (the leaderboard's number, on the
                # final evaluation's episodes); before it: the anytime curve.
                final = r.get("final_normalized")
                score = (final if abs(secs - 60 * m) < 1e-6 and final is not None
                         else float(curves.value_at(r.get("curve"), [60 * m])[0]))
                rows.append({"method": r["method"], "variant": variant(r), "minutes": m,
                             "seed": r["seed"], "normalized": float(score)})
    df = pd.DataFrame(rows, columns=["method", "variant", "minutes", "seed", "normalized"])
    if df.empty:
        raise ValueError(f"no finished runs on {task!r} with a wall-clock budget in "
                         f"{', '.join(str(s.root) for s in (store, *more_stores))}")
    several = df.groupby("method").variant.nunique()
    df["method"] = [f"{m} ({v})" if several[m] > 1 else m
                    for m, v in zip(df.method, df.variant)]
    return (df.groupby(["method", "minutes"]).normalized.agg(["mean", "std", "count"])
            .reset_index())


def ild_requests(task: str, seconds: float, truncations=(1, 10, 30), batches=(8, 32, 128),
                 seeds=(0,), preset: str | None = "cpu"):
    from bench.budget import Budget
    from bench.runner import RunRequest
    return [RunRequest(method="ild", task=task, seed=s, budget=Budget(seconds=seconds, evals=5),
                       preset=preset, overrides={"truncation": tr, "num_envs": b})
            for s in seeds for tr in truncations for b in batches]


def ild_table(store: Store, task: str, version: str | None = None) -> pd.DataFrame:
    """ILD's truncation x batch runs on `task`, of ILD `version` only (default: the
    registered one; an older ILD's records left in the store are not mixed in). A cell's
    seed counts once: the latest finished record at that budget stands for it
    (`ablation.latest_per`)."""
    from bench.ablation import ild_runs, latest_per
    latest = latest_per(ild_runs(store, task, version),
                        lambda r: (r["config"]["truncation"], r["config"]["num_envs"], r["seed"],
                                   r["budget"]["seconds"]))
    rows = []
    for r in latest.values():
        c = r["config"]
        rows.append({"truncation": c["truncation"], "batch": c["num_envs"], "seed": r["seed"],
                     "status": r["status"], "normalized": r["final_normalized"],
                     "updates": r["train_metrics"].get("train/updates"),
                     "env_steps": r["env_steps"],
                     "env_steps_per_s": r["env_steps"] / max(r["train_s"], 1e-9),
                     "budget_s": r["budget"]["seconds"]})
    df = pd.DataFrame(rows)
    return df.sort_values(["truncation", "batch", "seed"], ignore_index=True) if rows else df


UTD_RATIOS = (1.0, 0.5, 0.25)
UTD_METHODS = ("dac", "pwil")


def utd_requests(task: str, seconds: float, ratios=UTD_RATIOS, methods=UTD_METHODS,
                 seeds=range(3), preset: str | None = "cpu"):
    """One run per method, ratio and seed at the same wall-clock budget. Ratio 1 is each
    method's default (the original's schedule), so its cells share run ids with a plain
    sweep of the same budget and preset."""
    from bench.budget import Budget
    from bench.runner import RunRequest
    return [RunRequest(method=m, task=task, seed=s, budget=Budget(seconds=seconds),
                       preset=preset, overrides={"updates_per_step": float(u)})
            for m in methods for u in ratios for s in seeds]


def utd_runs(store: Store, task: str, seconds: float, methods=UTD_METHODS) -> pd.DataFrame:
    """One row per (method, ratio, seed): the finished runs of each method's registered
    version on `task` at the wall-clock budget `seconds`. A seed counts once: the latest
    finished record stands for it (`ablation.latest_per`)."""
    from bench.ablation import latest_per
    from bench.plugins import get_method
    versions = {m: str(get_method(m).version) for m in methods}
    runs = [r for r in store.records()
            if r["task"] == task and r["method"] in versions
            and str(r.get("method_version")) == versions[r["method"]]
            and r.get("status") in ("ok", "diverged")
            and abs(((r.get("budget") or {}).get("seconds") or -1) - seconds) < 1e-6
            and "updates_per_step" in (r.get("config") or {})]
    latest = latest_per(runs, lambda r: (r["method"], float(r["config"]["updates_per_step"]),
                                         r["seed"]))
    rows = []
    for (method, utd, seed), r in sorted(latest.items()):
        train_s = max(float(r.get("train_s") or 0.0), 1e-9)
        updates = (r.get("train_metrics") or {}).get("train/updates")
        rows.append({"method": method, "utd": utd, "seed": seed, "status": r["status"],
                     "normalized": r.get("final_normalized"), "env_steps": r["env_steps"],
                     "updates": updates, "env_steps_per_s": r["env_steps"] / train_s,
                     "updates_per_s": None if updates is None else updates / train_s})
    return pd.DataFrame(rows, columns=["method", "utd", "seed", "status", "normalized",
                                       "env_steps", "updates", "env_steps_per_s",
                                       "updates_per_s"])


def utd_table(store: Store, task: str, seconds: float, methods=UTD_METHODS) -> pd.DataFrame:
    """Per method and update-to-data ratio at one wall-clock budget: seeds, mean and std of
    the final normalized score, and the medians of env steps, updates and their rates.
    `score_vs_utd1` and `env_steps_vs_utd1` compare each row with the same method's ratio-1
    row of the same store (absent: NaN), so both sides ran on the same machine."""
    runs = utd_runs(store, task, seconds, methods)
    if runs.empty:
        raise ValueError(f"no finished DAC or PWIL runs on {task!r} at {seconds:g} s in "
                         f"{store.root}: run `ildbench tradeoff utd --task {task} --budget "
                         f"{seconds:g}s` first")
    df = (runs.groupby(["method", "utd"])
          .agg(seeds=("seed", "count"), mean=("normalized", "mean"),
               std=("normalized", "std"), env_steps=("env_steps", "median"),
               updates=("updates", "median"), env_steps_per_s=("env_steps_per_s", "median"),
               updates_per_s=("updates_per_s", "median"))
          .reset_index().sort_values(["method", "utd"], ascending=[True, False],
                                     ignore_index=True))
    base = df[df.utd == 1.0].set_index("method")
    df["score_vs_utd1"] = [m - base["mean"].get(meth, np.nan)
                           for meth, m in zip(df.method, df["mean"])]
    df["env_steps_vs_utd1"] = [e / base["env_steps"].get(meth, np.nan)
                               for meth, e in zip(df.method, df.env_steps)]
    return df


def plot_utd(df: pd.DataFrame, task: str, seconds: float, out: str) -> str:
    fig, ax = plt.subplots(figsize=(4.8, 3.4))
    for method, g in df.groupby("method"):
        ax.errorbar(g.env_steps, g["mean"], yerr=g["std"].fillna(0), marker="o",
                    label=method, capsize=3)
        for _, r in g.iterrows():
            ax.annotate(f"utd {r.utd:g}", (r.env_steps, r["mean"]), fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel(f"env steps in {seconds:g} s (median over seeds)")
    ax.set_ylabel("final normalized score")
    ax.set_title(f"{task}: update-to-data ratio at equal wall-clock")
    ax.legend(fontsize=7)
    return save_figure(fig, out, f"{task}_utd.png")


def _save(df: pd.DataFrame, task: str, part: str, out: str) -> list[str]:
    return write_table(df, os.path.join(out, f"{task}_{part}"))


def plot_backends(df: pd.DataFrame, task: str, out: str) -> str:
    ok = df[df.get("error", pd.Series([""] * len(df))).fillna("") == ""]
    fig, ax = plt.subplots(figsize=(4.8, 3.4))
    for _, r in ok.iterrows():
        for col, mk in (("fwd_steps_per_s", "o"), ("grad_steps_per_s", "s")):
            ax.scatter(r[col], r["pos_err_mean_m"], marker=mk)
            ax.annotate(f"{r['backend']} ({col[:4]})", (r[col], r["pos_err_mean_m"]),
                        fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel("env-steps/s (o forward, s gradient)")
    ax.set_ylabel(f"mean body position error vs {REFERENCE_BACKEND} (m)")
    ax.set_title(f"{task}: backend speed vs accuracy")
    return save_figure(fig, out, f"{task}_backends.png")


def plot_budget(df: pd.DataFrame, task: str, out: str) -> str:
    fig, ax = plt.subplots(figsize=(4.8, 3.4))
    for method, g in df.groupby("method"):
        ax.errorbar(g.minutes, g["mean"], yerr=g["std"].fillna(0), marker="o", label=method,
                    capsize=3)
    ax.set_xscale("log")
    ticks = sorted(df.minutes.unique())
    ax.set_xticks(ticks, [f"{m:g}" for m in ticks])
    ax.set_xticks([], minor=True)  # the log axis's own minor labels (6x10^-1) overprint 0.5
    ax.set_xlabel("training budget (minutes)")
    ax.set_ylabel("normalized score")
    ax.set_title(f"{task}: score vs budget")
    ax.legend(fontsize=7)
    return save_figure(fig, out, f"{task}_budget.png")


def plot_ild(df: pd.DataFrame, task: str, out: str) -> str:
    piv = df.groupby(["truncation", "batch"]).normalized.mean().unstack("batch")
    fig, ax = plt.subplots(figsize=(4.4, 3.4))
    im = ax.imshow(piv.to_numpy(), cmap="viridis", aspect="auto")
    ax.set_xticks(range(piv.shape[1]), [str(c) for c in piv.columns])
    ax.set_yticks(range(piv.shape[0]), [str(i) for i in piv.index])
    for (i, j), v in np.ndenumerate(piv.to_numpy()):
        ax.text(j, i, f"{v:.2f}", ha="center", va="center", color="w", fontsize=8)
    ax.set_xlabel("batch (parallel rollouts)")
    ax.set_ylabel("truncation length")
    ax.set_title(f"{task}: ILD final score at {df.budget_s.iloc[0]:g} s")
    fig.colorbar(im)
    return save_figure(fig, out, f"{task}_ild.png")


def known_tasks() -> list[str]:
    return [n for n in TASKS if n != "pointmass"]
