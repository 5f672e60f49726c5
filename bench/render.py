"""HTML renders (brax's own viewer) of the expert demo next to a learned policy.

Renders are made from matched states (per body: pos, rot, vel, ang; tasks/registry.py), which
the demo file holds and every run stores for its final policy's first evaluation episode
(`<run_id>.traj.npz` beside the record). Only positions and rotations are drawn. The page
`render_<task>.html` shows both viewers side by side; the viewer's JavaScript comes from
brax's CDN (as with brax.io.html), so viewing needs a browser with internet access, while
making the page does not.
"""
from __future__ import annotations

import html as _html
import os
import types

import numpy as np

from bench.store import Store
from tasks import make_task
from tasks.demo import load_demo


def states_from_matched(matched: np.ndarray, num_links: int) -> list:
    """(T, 13 * nb) matched states -> objects with `.x` (brax Transform) for the viewer."""
    from brax.base import Transform
    m = np.asarray(matched, np.float32)
    if m.ndim != 2 or m.shape[1] != 13 * num_links:
        raise ValueError(f"matched states of shape {m.shape} do not fit {num_links} bodies "
                         f"(expected (T, {13 * num_links}))")
    nb = num_links
    pos = m[:, :3 * nb].reshape(-1, nb, 3)
    rot = m[:, 3 * nb:7 * nb].reshape(-1, nb, 4)
    return [types.SimpleNamespace(x=Transform(pos=p, rot=r)) for p, r in zip(pos, rot)]


def viewer_html(task_name: str, matched: np.ndarray, height: int = 360) -> str:
    from brax.io import html
    task = make_task(task_name)
    sys = getattr(task.env.unwrapped, "sys", None)
    if sys is None:
        raise ValueError(f"task {task_name!r} has no brax system to draw; renders work on the "
                         "Brax tasks")
    return html.render(sys, states_from_matched(matched, sys.num_links()), height=height,
                       colab=False)


def pick_record(store: Store, task: str, method: str, seed: int | None = None) -> dict:
    recs = [r for r in store.records() if r["task"] == task and r["method"] == method
            and r.get("status") == "ok" and (seed is None or r["seed"] == seed)
            and os.path.exists(store.trajectory_path(r["run_id"]))]
    if not recs:
        raise ValueError(f"no finished {method!r} run on {task!r}"
                         f"{'' if seed is None else f' with seed {seed}'} with a stored "
                         f"trajectory in {store.root}; run one first (records made before "
                         "trajectories were stored have none)")
    return max(recs, key=lambda r: (r.get("final_normalized") or -np.inf)
               if seed is None else r["finished"])


def render_pair(store: Store, task: str, method: str, out_dir: str,
                seed: int | None = None) -> str:
    """Write render_<task>_<method>.html: the demo (left) and the method's final policy
    (right; the given seed, or its best-scoring seed)."""
    rec = pick_record(store, task, method, seed)
    t = make_task(task)
    demo = load_demo(t.spec.demo_path, t)
    left = viewer_html(task, demo.states[0])
    right = viewer_html(task, store.trajectory(rec["run_id"]))
    title = (f"{task}: expert demo (return {demo.expert_return:.1f}) vs {method} seed "
             f"{rec['seed']} (normalized {rec['final_normalized']:.3f}, budget "
             f"{rec['budget'].get('seconds')} s)")
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{_html.escape(title)}
</title><style>body{{font-family:sans-serif}} .row{{display:flex;gap:8px}}
.col{{flex:1}} iframe{{width:100%;height:400px;border:1px solid #ccc}}</style></head>
<body><h3>{_html.escape(title)}</h3><div class="row">
<div class="col"><b>expert demo</b><iframe srcdoc="{_html.escape(left)}"></iframe></div>
<div class="col"><b>{_html.escape(method)} (final policy, first evaluation episode)</b>
<iframe srcdoc="{_html.escape(right)}"></iframe></div></div></body></html>
"""
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, f"render_{task}_{method}.html")
    with open(path, "w") as f:
        f.write(page)
    return path


def cloth_panels(store: Store, methods=None, seed: int | None = None) -> list:
    """The runs a cloth render shows: per (training dynamics, method), the given seed or the
    best-scoring one (ties: the lowest seed), with a stored trajectory. Returns
    [(dynamics key, method, record)] sorted by dynamics (nominal first), then method."""
    recs = [r for r in store.records() if r["task"] == "cloth" and r.get("status") == "ok"
            and (methods is None or r["method"] in methods)
            and (seed is None or r["seed"] == seed)
            and os.path.exists(store.trajectory_path(r["run_id"]))]
    if methods is not None:
        missing = sorted(set(methods) - {r["method"] for r in recs})
        if missing:
            raise ValueError(f"no finished cloth run of {', '.join(missing)} with a stored "
                             f"trajectory in {store.root}; run one first, or leave the "
                             "method out")
    if not recs:
        raise ValueError(f"no finished cloth run{'' if seed is None else f' with seed {seed}'}"
                         f" with a stored trajectory in {store.root}; run one first")
    best: dict = {}
    for r in recs:
        key = ((r.get("train_dynamics") or {}).get("key") or "", r["method"])
        rank = (r.get("final_normalized") or -np.inf, -r["seed"])
        if key not in best or rank > best[key][0]:
            best[key] = (rank, r)
    return [(k[0] or "nominal", k[1], best[k][1]) for k in sorted(best)]


def _cloth_frames(states: np.ndarray, length: int) -> np.ndarray:
    """(T, D) -> (length, D): the episode padded with its last state (a run that ended early
    holds still)."""
    s = np.asarray(states, np.float32)
    return np.concatenate([s, np.repeat(s[-1:], max(0, length - len(s)), 0)])[:length]


def render_cloth(store: Store, out_dir: str, methods=None, seed: int | None = None,
                 every: int = 2, dpi: int = 50) -> str:
    """Write render_cloth.html: an animation (matplotlib, embedded frames; no internet needed
    to view it) of the cloth in the (z, y) side view, the expert demo beside each method's
    final policy, one row per training dynamics in the store. A run's panel is its first
    evaluation episode (the stored trajectory), played in the dynamics it was scored in; the
    demo is the noise-free expert's. Grippers are drawn as crosses, the pole as a red disc."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation
    from tasks.cloth import sim

    panels = cloth_panels(store, methods, seed)
    task = make_task("cloth")
    demo = np.asarray(load_demo(task.spec.demo_path, task).states[0], np.float32)
    rows = sorted({p[0] for p in panels}, key=lambda k: (k != "nominal", k))
    cols = sorted({p[1] for p in panels})
    grid = {(d, m): r for d, m, r in panels}
    length = max([len(demo)] + [len(store.trajectory(r["run_id"])) for _, _, r in panels])
    grip = 6 * sim.N
    fig, axes = plt.subplots(len(rows), len(cols) + 1, figsize=(2.6 * (len(cols) + 1),
                             2.6 * len(rows)), squeeze=False, sharex=True, sharey=True)
    drawn = []  # (cloth scatter, gripper line, frames)
    for i, dyn in enumerate(rows):
        for j, name in enumerate(["demo"] + cols):
            ax = axes[i][j]
            ax.add_patch(plt.Circle((sim.POLE_YZ[1], sim.POLE_YZ[0]), sim.POLE_RADIUS,
                                    color="red"))
            ax.set_xlim(-0.1, 0.7)
            ax.set_ylim(-0.05, 0.65)
            ax.set_aspect("equal")
            ax.tick_params(labelsize=6)
            if name == "demo":
                frames, title = demo, "expert demo\n(noise-free)"
            elif (dyn, name) in grid:
                r = grid[(dyn, name)]
                frames = np.asarray(store.trajectory(r["run_id"]), np.float32)
                title = (f"{name} seed {r['seed']}\n{dyn}: "
                         f"{r.get('final_normalized') or 0:.2f}")
            else:
                ax.set_title(f"{name}\n{dyn}: not run", fontsize=7)
                continue
            ax.set_title(title, fontsize=7)
            frames = _cloth_frames(frames, length)
            cloth = ax.scatter([], [], s=1, color="C0" if name == "demo" else f"C{j}")
            grippers, = ax.plot([], [], "kx", ms=5)
            drawn.append((cloth, grippers, frames))
        axes[i][0].set_ylabel(f"{dyn}\ny (height)", fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("z", fontsize=7)
    fig.tight_layout()

    def update(t):
        out = []
        for cloth, grippers, frames in drawn:
            x = frames[t, :grip].reshape(sim.N, 6)
            cloth.set_offsets(np.stack([x[:, 2], x[:, 1]], 1))
            g = frames[t, grip:grip + 8].reshape(2, 4)
            grippers.set_data(g[:, 2], g[:, 1])
            out += [cloth, grippers]
        return out

    anim = FuncAnimation(fig, update, frames=range(0, length, max(1, every)), blit=False)
    fig.set_dpi(dpi)
    page = anim.to_jshtml(fps=10, default_mode="loop")
    plt.close(fig)
    title = "cloth: the expert demo beside each method's final policy (score in the title)"
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, "render_cloth.html")
    with open(path, "w") as f:
        f.write(f"<!doctype html><html><head><meta charset=\"utf-8\"><title>{title}</title>"
                f"</head><body><h3>{title}</h3>{page}</body></html>\n")
    return path
