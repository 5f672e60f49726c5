"""Session 62: reacher's or inverted_pendulum's ILD update (its TASK_OVERRIDES config) with
pieces of `tasks.positional_joints` patched into brax's positional substep, paired in one
process (rounds of 8 updates per variant and 8 forwards; round 0 warms up):

    python results/positional_joints/scripts/pieces_pair.py TASK none,pj,step,hand [ROUNDS]

none: brax's substep; pj: brax's substep with `position_update` (the joints' update for
hinges and slides) alone; step: `positional_joints.step` without the hand-written VJPs;
hand: `positional_joints.step(hand=True)`, what ILD's `positional_joints` runs. Prints each
variant's median seconds per update, its speed-up over the first variant (median and range
over rounds) and update / forward (brax's forward rollout as `methods.ild.paired` times it).
"""
import contextlib, statistics, sys, time
import jax
import brax.positional.joints as pj
import tasks.positional_joints as P
from bench.malloc import reexec_with_hugepages
from methods.ild.benchmark import speed_setup
from methods.ild.config import ILDConfig
from methods.ild.paired import compiled_chunk, compiled_forward, parse_variant
from tasks import make_task
_orig = pj.position_update
@contextlib.contextmanager
def patched(v):
    if v == "pj":
        rows = P.joint_rows(TASK.env.unwrapped.sys)
        pj.position_update = lambda sys, state: P.position_update(sys, state, rows)
    import brax.positional.pipeline as bp
    ostep = bp.step
    if v in ("step", "hand"):
        rows = P.joint_rows(TASK.env.unwrapped.sys)
        bp.step = lambda sys, state, act, debug=False: P.step(sys, state, act, debug, rows=rows, hand=(v == "hand"))
    try: yield
    finally:
        pj.position_update = _orig; bp.step = ostep
def main():
    global TASK
    reexec_with_hugepages()
    task_name, vs = sys.argv[1], sys.argv[2].split(",")
    rounds = int(sys.argv[3]) if len(sys.argv) > 3 else 4
    cfg = parse_variant("task", 32, task_name)
    TASK = task = make_task(task_name); setup = speed_setup(task, cfg)
    timed = {}
    for v in vs:
        with patched(v): timed[v] = compiled_chunk(task, cfg, setup)
    fwd, params = compiled_forward(task, ILDConfig(num_envs=32), setup)
    sec = {v: [] for v in vs}; fs = []
    for r in range(rounds + 1):
        for v, (chunk, state, n) in timed.items():
            t0 = time.perf_counter()
            for _ in range(8): state = chunk(state, n)[0]
            jax.block_until_ready(state)
            if r: sec[v].append((time.perf_counter() - t0) / 8)
        t0 = time.perf_counter()
        for _ in range(8): jax.block_until_ready(fwd(params))
        if r: fs.append((time.perf_counter() - t0) / 8)
    for v in vs:
        up = [b / s for b, s in zip(sec[vs[0]], sec[v])]
        rat = [s / f for s, f in zip(sec[v], fs)]
        print(f"{task_name} {v}: {statistics.median(sec[v]):.4f} s, speedup {statistics.median(up):.3f}x [{min(up):.3f},{max(up):.3f}], update/forward {statistics.median(rat):.2f}x", flush=True)
main()
