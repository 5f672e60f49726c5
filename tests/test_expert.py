"""Expert training plumbing: recipes and overrides, best-evaluation checkpointing under brax's
callback order, the time limit, resume, and the shims for newer JAX."""
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench import expert
from tasks.jax_compat import clip_compat, device_put_replicated


def test_recipes_and_overrides():
    cfg = expert.ppo_config("walker2d", "gpu", overrides={"discounting": "0.99",
                                                          "batch_size": "1024",
                                                          "normalize_observations": "false"})
    assert cfg["discounting"] == 0.99 and cfg["batch_size"] == 1024
    assert isinstance(cfg["batch_size"], int) and cfg["normalize_observations"] is False
    assert expert.ppo_config("ant", "cpu", num_timesteps=5)["num_timesteps"] == 5
    with pytest.raises(ValueError, match="unknown PPO setting 'discount'.*discounting"):
        expert.ppo_config("ant", "gpu", overrides={"discount": "0.9"})
    with pytest.raises(ValueError, match="unknown PPO expert preset 'tpu'"):
        expert.ppo_config("ant", "tpu")
    with pytest.raises(ValueError, match="unknown SAC expert preset 'gpu'; presets: cpu"):
        expert.ppo_config("walker2d", "gpu", algorithm="sac")
    with pytest.raises(ValueError, match="unknown expert algorithm 'td3'.*ppo, sac"):
        expert.ppo_config("walker2d", algorithm="td3")
    assert [expert.default_algorithm(t) for t in ("acrobot", "swimmer", "walker2d", "hopper")] \
        == ["trajopt", "trajopt", "sac", "ppo"]
    sac = expert.ppo_config("walker2d", algorithm="sac", overrides={"grad_updates_per_step": "4"})
    assert sac["grad_updates_per_step"] == 4 and sac["episode_length"] == 1000
    with pytest.raises(ValueError, match="no PPO expert recipe for task 'pointmass'"):
        expert.ppo_config("pointmass", "gpu")
    with pytest.raises(ValueError, match="takes true or false"):
        expert.ppo_config("ant", "gpu", overrides={"normalize_observations": "yes"})
    with pytest.raises(ValueError, match="--steps must be positive"):
        expert.ppo_config("ant", "gpu", num_timesteps=0)


def _fake_ppo(evals, calls, interrupt_at=None):
    """brax PPO's callback order: initial evaluation, then its parameters; in the loop the
    parameters of step s first, then the evaluation of those same parameters. Ctrl-C
    (KeyboardInterrupt) after the evaluation of step `interrupt_at`."""
    def train(environment, seed, progress_fn, policy_params_fn, restore_params=None, **cfg):
        calls.append((restore_params, environment))
        p = lambda v: (np.float32(v), {"w": np.full(2, v, np.float32)},
                       {"v": np.float32(-v)})
        progress_fn(0, {"eval/episode_reward": evals[0]})
        policy_params_fn(0, None, p(evals[0]))
        for i, ret in enumerate(evals[1:], 1):
            policy_params_fn(i * 10, None, p(ret))
            progress_fn(i * 10, {"eval/episode_reward": ret})
            if i * 10 == interrupt_at:
                raise KeyboardInterrupt
        return None, None, None
    return train


@pytest.fixture
def fake_train(monkeypatch, tmp_path):
    from brax.training.agents.ppo import train as ppo_train
    written = {}

    def serialize(state):  # record what would be written, keyed by the tree's shape
        written.setdefault("states", []).append(jax.tree.map(np.asarray, state))
        return b"x"
    monkeypatch.setattr(expert.serialization, "msgpack_serialize", serialize)
    calls = []

    def run(evals, interrupt_at=None, **kw):
        monkeypatch.setattr(ppo_train, "train", _fake_ppo(evals, calls, interrupt_at))
        written.clear()
        path = expert.train_expert("ant", preset="gpu", out_dir=str(tmp_path), log=lambda *a: None,
                                   **kw)
        meta = json.load(open(tmp_path / "ant_expert.json"))
        policies = [s for s in written["states"] if "policy" in s]
        return path, meta, policies, calls
    return run


def test_the_best_evaluations_parameters_are_kept(fake_train):
    # Evaluation i scores the parameters of value i's list entry; the best is 7.0 at step 20.
    path, meta, policies, _ = fake_train([1.0, 3.0, 7.0, 2.0, float("nan")])
    assert path.endswith("ant_expert.msgpack")
    assert meta["best_eval_step"] == 20 and meta["best_eval_return"] == 7.0
    assert meta["complete"] is True and [e["step"] for e in meta["evals"]] == [0, 10, 20, 30, 40]
    # Written at each improvement (1, 3, 7), each time with the parameters evaluated.
    assert [float(s["policy"]["w"][0]) for s in policies] == [1.0, 3.0, 7.0]


def test_time_limit_stops_at_an_evaluation_and_keeps_the_best(fake_train):
    path, meta, policies, _ = fake_train([1.0, 5.0, 4.0, 9.0], time_limit_s=0.0)
    # The limit is checked after each evaluation past step 0: training stops after step 10.
    assert meta["complete"] is False and meta["best_eval_return"] == 5.0
    assert [e["step"] for e in meta["evals"]] == [0, 10]


def test_an_interrupted_training_keeps_the_best_and_says_so(fake_train):
    """Ctrl-C at the third evaluation leaves the best evaluation's parameters and a final
    record of every evaluation seen, marked interrupted (a finished run: stopped None)."""
    path, meta, policies, _ = fake_train([1.0, 6.0, 3.0, 9.0], interrupt_at=20)
    assert meta["complete"] is False and meta["stopped"] == "interrupted"
    assert meta["best_eval_return"] == 6.0 and [e["step"] for e in meta["evals"]] == [0, 10, 20]
    assert [float(s["policy"]["w"][0]) for s in policies] == [1.0, 6.0]
    _, meta, _, _ = fake_train([1.0, 2.0])
    assert meta["complete"] is True and meta["stopped"] is None
    _, meta, _, _ = fake_train([1.0, 5.0, 4.0], time_limit_s=0.0)
    assert meta["stopped"] == "time limit 0s"


def test_no_finite_evaluation_saves_nothing(fake_train):
    with pytest.raises(RuntimeError, match="no finite evaluation return"):
        fake_train([float("nan"), float("nan")])


def test_training_env_shaping_reaches_the_trainer_and_the_record(fake_train):
    _, meta, _, calls = fake_train([1.0, 2.0], env_overrides={"healthy_reward": "0.5",
                                                              "terminate_when_unhealthy": "false"})
    env = calls[-1][1].unwrapped
    assert env._healthy_reward == 0.5 and env._terminate_when_unhealthy is False
    assert meta["train_env"] == {"healthy_reward": 0.5, "terminate_when_unhealthy": False}
    # Without shaping the trainer gets the task's own environment.
    _, meta, _, calls = fake_train([1.0, 2.0])
    assert meta["train_env"] == {} and calls[-1][1] is expert.make_task("ant").env
    with pytest.raises(ValueError, match="brax:ant takes no argument 'healthy'.*healthy_reward"):
        expert.training_env_kwargs("ant", {"healthy": "1"})


def test_sac_expert_keeps_the_best_checkpoint_and_loads_as_a_policy(monkeypatch, tmp_path):
    """brax SAC hands out no parameters during training: it saves a checkpoint per evaluation
    (none for the untrained step-0 one) just before reporting it. The best evaluation's
    checkpoint becomes the expert file, scratch checkpoints are removed, and the file loads
    as a Policy that acts like brax's own SAC inference on those parameters."""
    from brax.training import checkpoint
    from brax.training.acme import running_statistics
    from brax.training.agents.sac import networks as sac_networks
    from brax.training.agents.sac import train as sac_train

    task = expert.make_task("ant")
    nets = expert._sac_networks(task)
    norm = running_statistics.init_state(jax.ShapeDtypeStruct((task.obs_size,), jnp.float32))

    def params(i):  # evaluation i's policy: the init drawn from key i
        return norm, nets.policy_network.init(jax.random.PRNGKey(i))
    saved, seen = {}, {}

    def fake_sac(environment, seed, progress_fn, checkpoint_logdir, **cfg):
        seen.update(cfg, env=environment)
        progress_fn(0, {"eval/episode_reward": 100.0})  # the untrained policy: no checkpoint
        for i, ret in enumerate([3.0, 8.0, 5.0], 1):
            path = os.path.join(checkpoint_logdir, f"{i * 10:012d}")
            os.makedirs(path)
            saved[path] = params(i)
            progress_fn(i * 10, {"eval/episode_reward": ret})
        seen["dir"] = checkpoint_logdir
    monkeypatch.setitem(expert.SAC_CONFIGS, "ant", expert.SAC_CONFIGS["walker2d"])
    monkeypatch.setattr(sac_train, "train", fake_sac)
    monkeypatch.setattr(checkpoint, "load", lambda path: list(saved[str(path)]))
    path = expert.train_expert("ant", algorithm="sac", out_dir=str(tmp_path),
                               log=lambda *a: None, overrides={"grad_updates_per_step": "4"})
    meta = json.load(open(tmp_path / "ant_expert.json"))
    assert meta["algorithm"] == "brax SAC" and meta["sac"]["grad_updates_per_step"] == 4
    assert seen["grad_updates_per_step"] == 4 and seen["episode_length"] == 1000
    # Step 0 scored 100 but has no checkpoint: the best kept is step 20's 8.0.
    assert meta["best_eval_step"] == 20 and meta["best_eval_return"] == 8.0
    assert not os.path.exists(seen["dir"])
    assert not os.path.exists(tmp_path / "ant_expert_value.msgpack")
    policy = expert.load_expert_policy("ant", path)
    obs = jax.random.normal(jax.random.PRNGKey(1), (task.obs_size,))
    want = sac_networks.make_inference_fn(nets)(params(2), deterministic=True)(
        obs, jax.random.PRNGKey(2))[0]
    got = policy.act(policy.params, obs, jax.random.PRNGKey(2), True)
    np.testing.assert_allclose(got, want, atol=1e-6)
    other = sac_networks.make_inference_fn(nets)(params(3), deterministic=True)(
        obs, jax.random.PRNGKey(2))[0]
    assert np.abs(np.asarray(got) - np.asarray(other)).max() > 1e-3
    with pytest.raises(ValueError, match="--resume continues PPO runs only"):
        expert.train_expert("ant", algorithm="sac", resume=str(tmp_path))
    with pytest.raises(ValueError, match="no SAC expert recipe for task 'hopper'"):
        expert.train_expert("hopper", algorithm="sac", out_dir=str(tmp_path))


def test_trajopt_expert_improves_and_replays_its_own_numbers(tmp_path):
    """The open-loop expert (acrobot's) on pointmass: Adam raises every start's return above
    its sinusoid's, the kept start is the one with the best held-out mean, and the stored
    table replayed by the loaded Policy earns what the record says."""
    cfg = dict(starts=3, steps=60, learning_rate=0.1, amplitude=1.0, min_freq=1.0,
               max_freq=3.0, select_episodes=4)
    path = expert.train_trajopt_expert("pointmass", seed=0, log=lambda *a: None,
                                       out_dir=str(tmp_path), config=cfg)
    steps0 = dict(cfg, steps=1)
    expert.train_trajopt_expert("pointmass", seed=0, log=lambda *a: None,
                                out_dir=str(tmp_path / "start"), config=steps0)
    meta = json.load(open(tmp_path / "pointmass_expert.json"))
    before = json.load(open(tmp_path / "start" / "pointmass_expert.json"))
    assert meta["algorithm"] == "trajopt" and meta["trajopt"] == cfg
    assert min(meta["select_returns"]) > max(before["select_returns"])
    assert meta["chosen_start"] == int(np.argmax(meta["select_returns"]))
    stored = expert.serialization.msgpack_restore(open(path, "rb").read())["actions"]
    task = expert.make_task("pointmass")
    env = task.env
    select_keys = jax.random.split(jax.random.split(jax.random.PRNGKey(0), 3)[2], 4)

    def replay(key):
        return jax.lax.scan(lambda s, a: (env.step(s, a), env.step(s, a).reward),
                            env.reset(key), jnp.asarray(stored))[1].sum()
    held_out = np.asarray(jax.vmap(replay)(select_keys)).mean()
    assert held_out == pytest.approx(meta["select_returns"][meta["chosen_start"]], abs=1e-3)
    # The loaded Policy plays the table whatever it observes.
    policy = expert.load_expert_policy("pointmass", path)
    r = expert.rollout(task, policy, jax.random.split(jax.random.PRNGKey(5), 2))
    np.testing.assert_array_equal(r["actions"][0], stored)
    np.testing.assert_array_equal(r["actions"][1], stored)
    with pytest.raises(ValueError, match="no trajectory-optimization recipe for task 'ant'"):
        expert.train_trajopt_expert("ant", out_dir=str(tmp_path))


def test_resume_names_missing_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="cannot resume 'ant'.*ant_expert_value.msgpack"):
        expert._load_for_resume(None, "ant", str(tmp_path))


def test_jax_compat_shims_match_jax():
    x = jnp.arange(-3.0, 4.0)
    np.testing.assert_array_equal(clip_compat(x, a_min=-1, a_max=2), jnp.clip(x, -1, 2))
    np.testing.assert_array_equal(clip_compat(a=x, a_max=0.5), jnp.clip(x, max=0.5))
    np.testing.assert_array_equal(clip_compat(x, min=0), jnp.clip(x, min=0))
    tree = {"a": jnp.ones((2, 3)), "b": jnp.float32(4.0)}
    ours = device_put_replicated(tree, jax.local_devices())
    if hasattr(jax, "device_put_replicated"):  # jax 0.7.2 (the pin) still has the original
        theirs = jax.device_put_replicated(tree, jax.local_devices())
        for k in tree:
            assert ours[k].shape == theirs[k].shape
            np.testing.assert_array_equal(ours[k], theirs[k])
    assert ours["a"].shape == (len(jax.local_devices()), 2, 3)


def test_committed_demos_name_their_experts_trainer():
    """A demo's meta records how its expert was trained (the expert json's algorithm)."""
    from tasks.registry import DATA_DIR
    want = {"walker2d": ("brax SAC", "sac"), "hopper": ("brax PPO", "ppo"),
            "acrobot": ("open-loop trajectory optimization through the task's physics",
                        "trajopt"),
            "swimmer": ("open-loop trajectory optimization through the task's physics",
                        "trajopt")}
    for task, (source, config_key) in want.items():
        meta = json.loads(str(np.load(os.path.join(DATA_DIR, f"{task}.npz"))["meta"]))
        assert meta["expert"]["source"] == source and config_key in meta["expert"], task
