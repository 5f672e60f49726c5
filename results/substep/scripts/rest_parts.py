"""Where the update's "rest" goes (session 59). ratio_floor.py finds hopper's update at
B = 128 about 0.2 s (20%) over the sum of its policy's, physics' and loss's gradients timed
apart, against 11 ms at B = 32. The rest could be what the update has and the parts lack
(the optimizer and the gradient's clean-up, fresh initial states each update, the
observations' gradient into the policy) or the cost of running policy and physics in one
loop. This times, interleaved in one process (every program compiled first, a warm-up round
not kept), seconds per call of:

    python results/substep/scripts/rest_parts.py TASK [--batch 128] [--rounds 6]
        [--repeats 4] [--out CSV]

- forward: the benchmark's forward row (brax's step as shipped, no gradient);
- update: ILD's update as TASK trains (`task_config`), as ratio_floor.py times it;
- update_fixed_init: the same with `resample_init=False` (the same initial states every
  update, no reset inside the update);
- grad: the update's gradient alone (no clean-up, clipping, Adam), keys as arguments;
- grad_obs_cut: grad with no gradient into the policy's observations (stop_gradient), which
  the parts never carry.
Then XLA's working memory (the benchmark's `temp_bytes`) of grad and of
ratio_floor.py's policy, physics and loss gradients.
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics

import jax

from bench.report import append_csv
from bench.runner import speed_settings
from methods.ild.benchmark import speed_setup, task_config, temp_bytes
from methods.ild.config import ILDConfig
from methods.ild.paired import compiled_chunk, compiled_forward
from methods.ild.train import make_rollout_loss, rollout_physics
from ratio_floor import loss_programs, physics_programs, policy_programs
from tasks import make_task
from timing import interleaved_seconds


class ObsCut:
    """The policy with no gradient into its observations."""

    def __init__(self, policy):
        self._policy = policy

    def __getattr__(self, name):
        return getattr(self._policy, name)

    def sample_batch(self, params, obs, keys, kernels_t, swish_remat=True):
        return self._policy.sample_batch(params, jax.lax.stop_gradient(obs), keys, kernels_t,
                                         swish_remat=swish_remat)

    def sample(self, params, obs, key):
        return self._policy.sample(params, jax.lax.stop_gradient(obs), key)


def temp_mib(f, args) -> float:
    return temp_bytes(f.lower(*args).compile()) / 2 ** 20


def run(task_name: str, batch: int, rounds: int, repeats: int):
    task = make_task(task_name)
    cfg = task_config(task_name, batch)
    setup = speed_setup(task, ILDConfig(num_envs=batch))
    policy, goals, norm, params, k = setup
    chunk, state, n = compiled_chunk(task, cfg, setup)
    fixed, fixed_state, _ = compiled_chunk(task, dataclasses.replace(cfg, resample_init=False),
                                           setup)
    fwd, fparams = compiled_forward(task, ILDConfig(num_envs=batch), setup)
    train = rollout_physics(task, cfg)
    args = (params, k[3], jax.random.split(k[2], batch))

    def grad_of(pol):
        loss_fn = make_rollout_loss(train, pol, goals, norm, cfg)
        return jax.jit(jax.grad(lambda p, key, ik: loss_fn(p, key, ik)[0]))

    calls = {"forward": (fwd, (fparams,)), "update": (lambda s: chunk(s, n)[0], (state,)),
             "update_fixed_init": (lambda s: fixed(s, n)[0], (fixed_state,)),
             "grad": (grad_of(policy), args), "grad_obs_cut": (grad_of(ObsCut(policy)), args)}
    seconds = interleaved_seconds(calls, rounds, repeats)
    memory = {"grad": temp_mib(*calls["grad"]),
              "policy_grad": temp_mib(*policy_programs(task, cfg, setup)[1]),
              "physics_grad": temp_mib(*physics_programs(task, cfg, setup)[2]),
              "loss_grad": temp_mib(*loss_programs(task, cfg, setup)[1])}
    return seconds, memory


def summary_lines(seconds: dict, memory: dict, title: str) -> list[str]:
    """Per program: median seconds per call, then its ratio to the forward and to the update
    (median and range over rounds, each round's programs against each other); then the
    working memory of grad against its parts'."""
    med = {k: statistics.median(v) for k, v in seconds.items()}

    def ratio(s, den):
        q = [x / y for x, y in zip(s, seconds[den])]
        return f"{statistics.median(q):.3f}x ({min(q):.3f}-{max(q):.3f}x)"

    parts = sum(v for k, v in memory.items() if k != "grad")
    return ([f"{title}; median s per call, / forward (rounds), / update (rounds):"]
            + [f"  {name:17s} {med[name]:.4f}  {ratio(s, 'forward')}  {ratio(s, 'update')}"
               for name, s in seconds.items()]
            + ["  working memory, MiB: " + ", ".join(f"{k} {v:.0f}" for k, v in memory.items())
               + f" (the parts' sum {parts:.0f})"])


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("task")
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--repeats", type=int, default=4)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    seconds, memory = run(a.task, a.batch, a.rounds, a.repeats)
    title = f"{a.task}, B = {a.batch}, {a.rounds} rounds x {a.repeats} calls"
    print("\n".join(summary_lines(seconds, memory, title)), flush=True)
    if a.out:
        settings = speed_settings()
        append_csv([{"task": a.task, "batch": a.batch, "program": name, "round": r,
                     "seconds": float(f"{x:.4g}"), **settings}
                    for name, s in seconds.items() for r, x in enumerate(s)], a.out)


if __name__ == "__main__":
    from bench.malloc import reexec_with_hugepages
    reexec_with_hugepages()  # glibc's huge-page tunable, as `ildbench` and the benchmark run
    main()
