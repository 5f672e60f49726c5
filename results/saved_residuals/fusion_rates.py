"""Session 73 probe: each XLA operation of ILD's update (the task's config, B = 32) profiled
(5 calls, `timing.xla_op_events`), with its time per call divided by the fused
computation's instructions x output elements (ns per instruction and element):

    python results/saved_residuals/fusion_rates.py ant [task,saved_residuals]

Prints the top operations by time and the fusions with the highest rate.
"""
import sys, re, math, collections
import pathlib
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "substep" / "scripts"))
import jax
from methods.ild.benchmark import speed_setup
from methods.ild.config import ILDConfig
from methods.ild.paired import compiled_chunk, parse_variant
from tasks import make_task
from timing import xla_op_events
task_name = sys.argv[1]; variant = sys.argv[2] if len(sys.argv) > 2 else "task"
task = make_task(task_name)
base = ILDConfig(num_envs=32)
setup = speed_setup(task, base)
chunk, state, n = compiled_chunk(task, parse_variant(variant, 32, task_name), setup)
hlo = chunk.lower(state, n).compile().as_text()
calls = 5
time_ns, count = xla_op_events(lambda: [jax.block_until_ready(chunk(state, n)) for _ in range(calls)], by_name=True)
comps = {}; cur = None; defs = {}
for line in hlo.split("\n"):
    if not line.startswith(" ") and line.rstrip().endswith("{") and "(" in line:
        cur = re.match(r"^(?:ENTRY )?%?(\S+)", line).group(1); comps[cur] = []; continue
    if line.startswith("}"): cur = None; continue
    if cur is not None and line.strip():
        comps[cur].append(line)
        m = re.match(r"\s*(?:ROOT )?%(\S+) = (\S+) (\w[\w-]*)\(", line)
        if m: defs[m.group(1)] = (m.group(2), m.group(3), line)
def elems(shape):
    tot = 0
    for m in re.finditer(r"[fsu]\d+\[([\d,]*)\]", shape):
        tot += math.prod(int(x) for x in m.group(1).split(",") if x) if m.group(1) else 1
    return tot
rows = []
for name, ns in time_ns.items():
    if name not in defs: continue
    shape, op, line = defs[name]
    m = re.search(r"calls=%?([\w.\-]+)", line)
    ninstr = len(comps.get(m.group(1), [])) if (m and op == "fusion") else 1
    e = elems(shape)
    per_call = ns / max(count[name], 1)
    rows.append((ns / calls, name, op, shape[:40], count[name] // calls, per_call, ninstr, e,
                 per_call / max(ninstr * e, 1)))
rows.sort(reverse=True)
tot = sum(r[0] for r in rows)
print(f"total profiled {tot/1e6:.1f} ms per call")
print("top by time:")
for r in rows[:40]:
    print(f"  {r[0]/1e3:8.1f} us/update {r[1][:36]:36s} {r[3]:36s} x{r[4]:<5d} {r[5]/1e3:7.2f} us each instr {r[6]:4d} elems {r[7]:6d} {r[8]:.3f} ns/ie")
print("fusions with the highest ns per instr*elem (>= 1 ms per update):")
for r in sorted([r for r in rows if r[0] > 1e6 and r[2] == "fusion"], key=lambda r: -r[8])[:30]:
    print(f"  {r[0]/1e3:8.1f} us/update {r[1][:36]:36s} {r[3]:36s} x{r[4]:<5d} {r[5]/1e3:7.2f} us each instr {r[6]:4d} elems {r[7]:6d} {r[8]:.3f} ns/ie")
