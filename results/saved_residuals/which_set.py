"""Session 74's probe: which residuals the substep checkpoint should save. `methods.ild.paired`
with three variants in one process: ILD's update as the task trained before session 74
(`task,saved_residuals=false` in effect: the run was made before the task override, as
`task`), with `SAVED_RESIDUALS` saved (`task,saved_residuals`), and with to_world's one
state-dependent residual (p, the links' offsets from their centres of mass) saved as well
(the last variant: a differently spelled `task,saved_residuals`, compiled while
`SAVED_RESIDUALS` names to_world too). to_world's forward is re-wrapped here with p named;
the names do nothing without a policy that lists them.

    python results/saved_residuals/which_set.py T results/saved_residuals/which_set_session74_T.csv

It calls `paired.main` in this process, so it ran without the huge-page tunable that
`python -m methods.ild.paired` re-executes itself with (the CSVs' `malloc_hugetlb` is
empty): its seconds are slower than the other paired files', its ratios between variants
are like for like. Session 74 ran it at commit d4c3cb8, humanoid on core 0 beside ant on
core 1.

Session 75 ran it with 10 rounds (the optional third argument, ROUNDS; default 6) on ant
alone, core 1, core 0 idle, with the tunable set by hand:

    GLIBC_TUNABLES=glibc.malloc.hugetlb=1 taskset -c 1 python results/saved_residuals/which_set.py
        ant results/saved_residuals/which_set_session75_alone_ant.csv 10

Since session 74's task override the first two variants are the same config (an A/A pair:
what the rounds' noise alone moves a median), the third adds to_world's residual."""
import sys
import jax
from jax.ad_checkpoint import checkpoint_name
import tasks.spring_adjoint as sa
from methods.ild import paired

_TOW = "spring_adjoint.to_world"


def _fwd(pos_i, rot_i, vel_i, ang_i, c):
    out, (rot_i, ang_i, c, p) = sa._to_world_forward(pos_i, rot_i, vel_i, ang_i, c)
    return out, (rot_i, ang_i, c, checkpoint_name(p, _TOW))


@jax.custom_vjp
def _to_world(pos_i, rot_i, vel_i, ang_i, c):
    return sa._to_world_forward(pos_i, rot_i, vel_i, ang_i, c)[0]


_to_world.defvjp(_fwd, sa._to_world_bwd)
sa._to_world = _to_world

variants = ["task", "task,saved_residuals", "task,saved_residuals,saved_residuals=true"]
orig = paired.compiled_chunk
calls = [0]
BASE = sa.SAVED_RESIDUALS


def compiled_chunk(task, cfg, setup):
    calls[0] += 1
    sa.SAVED_RESIDUALS = BASE + ((_TOW,) if calls[0] == len(variants) else ())
    print("compile", calls[0], sa.SAVED_RESIDUALS, flush=True)
    try:
        return orig(task, cfg, setup)
    finally:
        sa.SAVED_RESIDUALS = BASE


paired.compiled_chunk = compiled_chunk
args = ["--task", sys.argv[1], "--rounds", sys.argv[3] if len(sys.argv) > 3 else "6",
        "--repeats", "8", "--apg-physics", "none",
        "--forward", "--out", sys.argv[2]]
for v in variants:
    args += ["--variant", v]
paired.main(args)
