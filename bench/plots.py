"""Plots from the results store (matplotlib, headless)."""
from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from bench.perturb import FAMILIES  # noqa: E402
from bench.store import Store  # noqa: E402


def save_figure(fig, out_dir: str, name: str) -> str:
    """Lay out, write <out_dir>/<name> (PNG, 100 dpi) and close the figure."""
    fig.tight_layout()
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, name)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def robustness_frame(store: Store, task: str) -> pd.DataFrame:
    """One row per (method, seed, family, magnitude) from runs' transfer entries."""
    rows = []
    for r in store.records():
        if r["task"] != task or r["status"] not in ("ok", "diverged"):
            continue
        rows.append({"method": r["method"], "seed": r["seed"], "family": "nominal",
                     "magnitude": 0.0, "normalized": r["final_normalized"]})
        for v in (r.get("transfer") or {}).values():
            rows.append({"method": r["method"], "seed": r["seed"], "family": v["family"],
                         "magnitude": v["magnitude"], "normalized": v["normalized"]})
    return pd.DataFrame(rows, columns=["method", "seed", "family", "magnitude", "normalized"])


def robustness_plot(store: Store, task: str, out_dir: str) -> str:
    """Normalized score vs perturbation magnitude, one panel per family, one line per
    method (mean over seeds, min-max band). Magnitude 0 is the nominal score."""
    df = robustness_frame(store, task)
    if df.empty:
        raise ValueError(f"no finished runs for task {task!r} in {store.root}; run with "
                         "--robustness (or --transfer) first")
    nominal = df[df.family == "nominal"]
    fams = [f for f in FAMILIES if (df.family == f).any()]
    fig, axes = plt.subplots(1, max(len(fams), 1), figsize=(3.2 * max(len(fams), 1), 3),
                             sharey=True, squeeze=False)
    for ax, fam in zip(axes[0], fams):
        part = pd.concat([df[df.family == fam], nominal.assign(family=fam)])
        for method, g in part.groupby("method"):
            s = g.groupby("magnitude").normalized.agg(["mean", "min", "max"]).sort_index()
            ax.plot(s.index, s["mean"], marker="o", label=method)
            ax.fill_between(s.index, s["min"], s["max"], alpha=0.2)
        ax.set_title(fam)
        ax.set_xlabel("magnitude")
        ax.axhline(1.0, color="grey", lw=0.5, ls="--")
    axes[0][0].set_ylabel("normalized score")
    axes[0][-1].legend(fontsize=8)
    fig.suptitle(f"{task}: robustness (1.0 = expert under the same perturbation)")
    return save_figure(fig, out_dir, f"robustness_{task}.png")


def training_frame(store: Store, task: str, method: str,
                   version: str | None = None) -> pd.DataFrame:
    """One row per (run, evaluation) of `method` on `task` (at `version`; None: every
    version): seed, env steps, the normalized score, and each training metric the method
    had last reported before that evaluation (the curve point's `train`)."""
    rows = []
    for r in store.records():
        if (r["task"] != task or r["method"] != method or r["status"] not in ("ok", "diverged")
                or (version is not None and r["method_version"] != version)):
            continue
        for i, point in enumerate(r["curve"]):
            rows.append({"run_id": r["run_id"], "seed": r["seed"], "point": i,
                         "env_steps": point["env_steps"], "normalized": point["normalized"],
                         **(point.get("train") or {})})
    return pd.DataFrame(rows)


def training_plot(store: Store, task: str, method: str, out_dir: str,
                  metrics: list[str] | None = None, version: str | None = None) -> str:
    """The normalized score and the training metrics against env steps, one panel each, one
    line per run (labelled by seed): what the learner was doing when its score moved.
    `metrics`: the metric keys to draw (default: every one the runs reported but the
    throughput ones, `speed/...`)."""
    df = training_frame(store, task, method, version)
    if df.empty:
        raise ValueError(f"no finished {method!r} runs on {task!r}"
                         + (f" at version {version}" if version else "") + f" in "
                         f"{store.root}; run them first, or check --store, --task and --method")
    known = [c for c in df.columns
             if c not in ("run_id", "seed", "point", "env_steps", "normalized")]
    if metrics is None:
        metrics = [c for c in known if not c.startswith("speed/") and df[c].notna().any()]
    unknown = [m for m in metrics if m not in known]
    if unknown:
        raise ValueError(f"unknown metric(s) {', '.join(unknown)} for {method!r} on {task!r}; "
                         f"the runs reported: {', '.join(known) or 'none'}")
    panels = ["normalized"] + list(metrics)
    cols = min(4, len(panels))
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    for ax, key in zip(axes.flat, panels):
        for (seed, run), g in df.groupby(["seed", "run_id"], sort=True):
            g = g.sort_values("point")
            ax.plot(g.env_steps, g[key], marker=".", label=f"seed {seed}")
        ax.set_title(key, fontsize=9)
        ax.set_xlabel("env steps", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"{method} on {task}: score and training metrics against env steps")
    return save_figure(fig, out_dir, f"train_{task}_{method}.png")


def cloth_paths_plot(store: Store, out_dir: str) -> str:
    """What the cloth's final policies do: per method, the two grippers' paths in the
    (z, y) side view of the first evaluation episode (the stored trajectory), the demo's in
    black, the pole as a circle, each run's final cloth as dots; one line per (seed,
    training dynamics), solid where the run succeeded."""
    import numpy as np
    from tasks import make_task
    from tasks.cloth import sim
    from tasks.demo import load_demo
    task = make_task("cloth")
    demo = np.asarray(load_demo(task.spec.demo_path, task).states[0])
    runs = [r for r in store.records() if r["task"] == "cloth" and r["status"] == "ok"
            and store.trajectory(r["run_id"]) is not None]
    if not runs:
        raise ValueError(f"no finished cloth runs with a stored trajectory in {store.root}")
    methods = sorted({r["method"] for r in runs})
    fig, axes = plt.subplots(1, len(methods), figsize=(4 * len(methods), 3.6), squeeze=False,
                             sharex=True, sharey=True)
    grip = 6 * sim.N  # the grippers' (x, y, z, r) follow the particles' (x, y, z, v)
    for ax, method in zip(axes[0], methods):
        for g in (0, 1):
            ax.plot(demo[:, grip + 4 * g + 2], demo[:, grip + 4 * g + 1], color="black",
                    lw=2, label="demo" if g == 0 else None)
        for i, r in enumerate(sorted((r for r in runs if r["method"] == method),
                                     key=lambda r: (r["seed"], str(r.get("train_dynamics"))))):
            states = store.trajectory(r["run_id"])
            dyn = (r.get("train_dynamics") or {}).get("key", "nominal")
            ok = (r.get("final_normalized") or 0) >= 0.5
            color = f"C{i}"
            for g in (0, 1):
                ax.plot(states[:, grip + 4 * g + 2], states[:, grip + 4 * g + 1], color=color,
                        ls="-" if ok else "--", lw=1,
                        label=f"seed {r['seed']} {dyn}: {r['final_normalized']:.2f}"
                        if g == 0 else None)
            cloth = states[-1, :grip].reshape(sim.N, 6)
            ax.scatter(cloth[:, 2], cloth[:, 1], s=1, color=color, alpha=0.3)
        ax.add_patch(plt.Circle((sim.POLE_YZ[1], sim.POLE_YZ[0]), 0.01, color="red"))
        ax.set_title(method)
        ax.set_xlabel("z")
        ax.legend(fontsize=6)
    axes[0][0].set_ylabel("y (height)")
    fig.suptitle("cloth: gripper paths of the first evaluation episode (dashed: failed), "
                 "final cloth as dots, pole in red")
    return save_figure(fig, out_dir, "cloth_paths.png")
