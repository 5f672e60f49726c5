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
