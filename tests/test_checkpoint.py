"""A run with an env-step budget that is stopped part way resumes from its last checkpoint and
ends with the record it would have had if never stopped (DAC and PWIL on pointmass)."""
import math
import os

import numpy as np
import pytest
import torch

from bench.budget import Budget
from bench.evaluator import EvalConfig
from bench.runner import RunContext, RunRequest, execute, prepare
from bench.store import Store
from methods.common.sb3 import seed_everything
from tests.test_sb3 import small_learner

TINY = dict(actor_hidden="16,16", critic_hidden="16,16", learning_starts=256, batch_size=32,
            num_envs=8, steps_per_collect=64, report_every=256)
EXTRA = {"dac": dict(disc_hidden="16,16", disc_batch=32, actor_start_updates=64),
         "pwil": dict(prefill=512)}


class Stop(BaseException):
    """A stopped process: not an error the runner records, so nothing is written."""


def _request(method):
    return RunRequest(method=method, task="pointmass", seed=3,
                      budget=Budget(env_steps=1536, evals=3),
                      overrides={**TINY, **EXTRA[method]}, eval=EvalConfig(num_episodes=4))


def _same_numbers(a, b):
    keys = ("env_steps", "return", "normalized", "length")
    assert [[p[k] for k in keys] for p in a["curve"]] == [[p[k] for k in keys]
                                                         for p in b["curve"]]
    assert a["final_return"] == b["final_return"] and a["env_steps"] == b["env_steps"]
    for k, v in a["train_metrics"].items():
        if not k.startswith("speed/"):
            assert b["train_metrics"][k] == v, k


@pytest.mark.parametrize("method", ["dac", "pwil"])
def test_a_stopped_run_resumes_from_its_checkpoint_to_the_same_record(tmp_path, monkeypatch,
                                                                        method):
    whole, _ = execute(prepare(_request(method)), Store(str(tmp_path / "whole")),
                       log=lambda s: None, checkpoint_every_s=math.inf)
    assert whole["status"] == "ok" and "resumed" not in whole

    store = Store(str(tmp_path / "stopped"))
    p = prepare(_request(method))
    save = RunContext.checkpoint

    def save_then_stop(self, state, env_steps):
        save(self, state, env_steps)
        if env_steps >= 700:  # past the first evaluation (512 env steps)
            raise Stop(env_steps)
    monkeypatch.setattr(RunContext, "checkpoint", save_then_stop)
    with pytest.raises(Stop) as stop:
        execute(p, store, log=lambda s: None, checkpoint_every_s=0.0)
    stopped_at = stop.value.args[0]
    assert store.get(p.run_id) is None and os.path.exists(store.checkpoint_path(p.run_id))
    monkeypatch.setattr(RunContext, "checkpoint", save)

    resumed, skipped = execute(p, store, log=lambda s: None, checkpoint_every_s=math.inf)
    assert not skipped and resumed["status"] == "ok"
    assert [r["env_steps"] for r in resumed["resumed"]] == [stopped_at]
    assert not os.path.exists(store.checkpoint_path(p.run_id))  # gone with the record
    assert len(resumed["curve"]) == len(whole["curve"]) == 3  # at 512, 1024 and the end
    _same_numbers(whole, resumed)


def test_force_starts_a_cell_afresh_and_a_seconds_budget_never_checkpoints(tmp_path,
                                                                          monkeypatch):
    store = Store(str(tmp_path))
    p = prepare(_request("pwil"))
    path = store.checkpoint_path(p.run_id)
    os.makedirs(os.path.dirname(path))
    with open(path, "wb") as f:
        f.write(b"not a checkpoint")  # resuming from it would fail
    rec, _ = execute(p, store, force=True, log=lambda s: None, checkpoint_every_s=math.inf)
    assert rec["status"] == "ok" and "resumed" not in rec and not os.path.exists(path)
    ctx = RunContext(Budget(seconds=60), None, 0, checkpoint_path=path, checkpoint_every_s=0)
    assert not ctx.checkpointing and not ctx.checkpoint_due() and ctx.resume() is None


@pytest.mark.parametrize("method", ["dac", "pwil"])
def test_learning_one_collection_per_call_equals_one_call_over_the_budget(method):
    """The learner runs SB3's learn() once per collection so that it can checkpoint between
    two; that is the same computation as the single learn() it replaces, to the bit."""
    small = dict(actor_hidden=(16,), critic_hidden=(16,), num_envs=8, steps_per_collect=64,
                 learning_starts=128, batch_size=32)

    def build():
        seed_everything(5)
        return small_learner(method, "pointmass", small, dict(
            disc_hidden=(16,), disc_batch=32, actor_start_updates=32), seed=5,
            pwil=dict(prefill=512))[0]
    one = build().learn(total_timesteps=640)
    chunked = build()
    for _ in range(10):
        chunked.learn(total_timesteps=64, reset_num_timesteps=False)
    assert chunked.num_timesteps == one.num_timesteps == 640
    assert chunked._n_updates == one._n_updates > 0
    for (k, a), b in zip(one.policy.state_dict().items(), chunked.policy.state_dict().values()):
        assert torch.equal(a, b), k
    np.testing.assert_array_equal(one.replay_buffer.observations,
                                  chunked.replay_buffer.observations)
