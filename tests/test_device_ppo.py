"""DevicePPO: rollouts through the batched env's torch interface, on CPU Warp here.

What a user relies on: the device path collects the same rollout as SB3's VecEnv path from the
same seed (observations, actions, rewards, dones, values, advantages, episode statistics and
VecNormalize statistics) and makes the same update; its hot loop uses neither the VecEnv methods
nor per-step host copies; it trains, saves and loads as a normal SB3 model; and with any other
env it is SB3's PPO.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

pytest.importorskip("mujoco_warp", reason="the batched backend needs the mujoco-warp extra")

from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.buffers import DictRolloutBuffer  # noqa: E402
from stable_baselines3.common.logger import configure  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize  # noqa: E402

import sb3_divmorph  # noqa: E402,F401  (policy aliases)
import unimal_envs  # noqa: E402,F401
from sb3_divmorph.algos.device_ppo import DeviceDictRolloutBuffer, DevicePPO, HostTransferCounter  # noqa: E402
from unimal_envs.batched import make_batched_env  # noqa: E402
from unimal_envs.batched.env import BatchedUnimalEnv  # noqa: E402
from unimal_envs.morphology.loader import morphology_files  # noqa: E402

ROBOTS = morphology_files("train")[:2]
TINY = dict(d_model=16, n_layers=1, ff_dim=32, exteroception=dict(hfield=[8], goal=[4], object=[4]))
POLICIES = {"MetaMorphPolicy": TINY, "DivMorphPolicy": dict(TINY, n_morph_tailors=4, n_task_tailors=4, top_k_morph=2, top_k_task=2)}
NORM_KEYS = ["proprioceptive", "hfield"]


def batched(task: str = "VT", max_episode_steps: int = 5, worlds: int = 2) -> VecNormalize:
    """2 robots x ``worlds`` worlds, monitored and normalised as the pipeline wraps them."""
    env = make_batched_env(
        task, morphologies=ROBOTS, worlds_per_robot=worlds, device="cpu", seed=0, max_episode_steps=max_episode_steps, terrain_variants=2
    )
    return VecNormalize(VecMonitor(env), norm_obs_keys=NORM_KEYS)


def first_rollout(model):
    """Collect one rollout as ``learn`` would, without the update."""
    _, callback = model._setup_learn(model.n_steps * model.n_envs, None)
    callback.on_training_start(locals(), globals())
    assert model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)
    return model.rollout_buffer


@pytest.mark.parametrize("policy", list(POLICIES))
def test_the_device_path_collects_the_same_first_rollout_and_makes_the_same_update_as_sb3s_vecenv_path(policy):
    # 8 steps with a 5-step time limit: every world is truncated once (bootstrapped from its final
    # observation) and auto-reset; observations and rewards go through VecNormalize.
    kwargs = dict(n_steps=8, batch_size=32, n_epochs=1, seed=0, policy_kwargs=POLICIES[policy])
    # one after the other: each model seeds torch's global generator, which samples the actions
    sb3 = PPO(policy, batched(), **kwargs)
    ref = first_rollout(sb3)
    device = DevicePPO(policy, batched(), **kwargs)
    buf = first_rollout(device)
    assert isinstance(ref, DictRolloutBuffer) and isinstance(buf, DeviceDictRolloutBuffer)
    assert ref.episode_starts[5].all() and buf.episode_starts[5].all(), "every world was truncated after 5 steps"

    obs = buf.stacked_observations()
    for key in ref.observations:
        np.testing.assert_allclose(obs[key].numpy(), ref.observations[key], atol=1e-4, err_msg=key)
    for name in ("actions", "rewards", "episode_starts", "values", "log_probs", "advantages", "returns"):
        np.testing.assert_allclose(getattr(buf, name).numpy(), getattr(ref, name), atol=1e-5, err_msg=name)
    # episode statistics (VecMonitor's, kept in tensors) and the VecNormalize statistics written back
    assert [e["l"] for e in device.ep_info_buffer] == [e["l"] for e in sb3.ep_info_buffer] == [5] * 4
    np.testing.assert_allclose([e["r"] for e in device.ep_info_buffer], [e["r"] for e in sb3.ep_info_buffer], atol=1e-5)
    ref_norm, norm = sb3.get_vec_normalize_env(), device.get_vec_normalize_env()
    for key in NORM_KEYS:
        assert norm.obs_rms[key].count == ref_norm.obs_rms[key].count == pytest.approx(1e-4 + 9 * 4)
        np.testing.assert_allclose(norm.obs_rms[key].mean, ref_norm.obs_rms[key].mean, atol=1e-5)
        np.testing.assert_allclose(norm.obs_rms[key].var, ref_norm.obs_rms[key].var, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(norm.ret_rms.var, ref_norm.ret_rms.var, rtol=1e-5)
    np.testing.assert_allclose(norm.returns, ref_norm.returns, atol=1e-5)

    # One minibatch of the whole rollout: the gradient does not depend on the order, so SB3's
    # update on either buffer gives the same weights (the device buffer's samples are aligned).
    sb3.train()
    device.train()
    for (name, p), q in zip(sb3.policy.named_parameters(), device.policy.parameters()):
        np.testing.assert_allclose(q.detach().numpy(), p.detach().numpy(), atol=1e-5, err_msg=name)


def test_gae_bootstrapping_and_minibatches_match_sb3s_rollout_buffer_on_the_same_data():
    space = spaces.Dict({"moving": spaces.Box(-1, 1, (3,)), "fixed": spaces.Box(-1, 1, (2,))})
    action_space = spaces.Box(-1, 1, (2,))
    steps, envs = 6, 3
    ref = DictRolloutBuffer(steps, space, action_space, "cpu", gae_lambda=0.9, gamma=0.95, n_envs=envs)
    buf = DeviceDictRolloutBuffer(steps, space, action_space, "cpu", gae_lambda=0.9, gamma=0.95, n_envs=envs, static_keys=["fixed"])
    rng = np.random.default_rng(0)
    fixed = rng.normal(size=(envs, 2)).astype(np.float32)
    for _ in range(steps):
        obs = {"moving": rng.normal(size=(envs, 3)).astype(np.float32), "fixed": fixed}
        action = rng.normal(size=(envs, 2)).astype(np.float32)
        reward = rng.normal(size=envs).astype(np.float32)
        start = (rng.random(envs) < 0.3).astype(np.float32)
        value, log_prob = torch.randn(envs, 1), torch.randn(envs)
        ref.add(obs, action, reward, start, value, log_prob)
        buf.add(
            {k: torch.as_tensor(v) for k, v in obs.items()},
            torch.as_tensor(action),
            torch.as_tensor(reward),
            torch.as_tensor(start),
            value,
            log_prob,
        )
    last, dones = torch.randn(envs), np.array([True, False, True])
    ref.compute_returns_and_advantage(last, dones)
    buf.compute_returns_and_advantage(last, torch.as_tensor(dones))
    np.testing.assert_allclose(buf.advantages.numpy(), ref.advantages, atol=1e-6)
    np.testing.assert_allclose(buf.returns.numpy(), ref.returns, atol=1e-6)

    list(ref.get(4))  # SB3 flattens its arrays (env-major); the device buffer gathers the same order
    everything = buf._get_samples(torch.arange(steps * envs))
    expected = ref._get_samples(np.arange(steps * envs))
    for a, b in zip(everything[1:], expected[1:]):
        np.testing.assert_allclose(a.numpy(), b.numpy().reshape(a.shape), atol=1e-6)
    for key in space.spaces:
        np.testing.assert_allclose(everything.observations[key].numpy(), expected.observations[key].numpy(), atol=1e-6)
    batches = list(buf.get(4))
    assert [len(b.actions) for b in batches] == [4, 4, 4, 4, 2]
    seen = torch.cat([b.old_log_prob for b in batches]).sort().values
    assert torch.equal(seen, buf.log_probs.flatten().sort().values), "every sample once per epoch"


def test_the_hot_loop_stays_on_the_device(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("DevicePPO went through the numpy VecEnv interface")

    for name in ("reset", "step_async", "step_wait", "_numpy"):
        monkeypatch.setattr(BatchedUnimalEnv, name, refuse)
    model = DevicePPO("MetaMorphPolicy", batched(max_episode_steps=3), n_steps=8, batch_size=32, n_epochs=1, seed=0, policy_kwargs=TINY)
    model.learn(2 * 8 * 4)  # would raise through `refuse` if any VecEnv method ran
    assert model.num_timesteps == 64 and len(model.ep_info_buffer) >= 8

    # Host copies per rollout do not grow with its length; waits for the device are at most 2 a step
    # (the env's auto-reset check and the truncation check).
    counts = {}
    for steps in (4, 8):
        with HostTransferCounter() as counter:
            model.collect_rollouts(model.env, model._init_callback(None), model.rollout_buffer, steps)
        counts[steps] = counter.counts
    assert counts[4]["to_host"] == counts[8]["to_host"] and counts[4]["to_device"] == counts[8]["to_device"], counts
    assert counts[8]["to_host_bytes"] < 64 * 1024, counts  # normaliser statistics and episode records
    assert counts[8]["syncs"] - counts[4]["syncs"] <= 2 * 4, counts


def test_device_ppo_trains_saves_and_loads_as_a_normal_sb3_model(tmp_path):
    venv = batched("FT", max_episode_steps=8)
    model = DevicePPO("DivMorphPolicy", venv, n_steps=8, batch_size=16, n_epochs=2, seed=0, policy_kwargs=POLICIES["DivMorphPolicy"])
    model.set_logger(configure(str(tmp_path / "log"), ["csv"]))
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(3 * 8 * 4)
    assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters()))
    assert model.timings["rollout"] > 0 and model.timings["update"] > 0
    progress = (tmp_path / "log" / "progress.csv").read_text().splitlines()
    header = progress[0].split(",")
    assert "rollout/ep_rew_mean" in header and "train/explained_variance" in header
    assert progress[-1].split(",")[header.index("rollout/ep_len_mean")] not in ("", "nan")
    # VecNormalize holds what the device normaliser learnt: 1 reset + 24 steps of 4 worlds
    assert venv.obs_rms["proprioceptive"].count == pytest.approx(1e-4 + 4 * 25)

    model.save(tmp_path / "model")
    venv.save(str(tmp_path / "vecnormalize.pkl"))
    loaded_env = VecNormalize.load(str(tmp_path / "vecnormalize.pkl"), venv.venv)
    loaded = DevicePPO.load(tmp_path / "model", env=loaded_env)
    plain = PPO.load(tmp_path / "model")
    obs = loaded_env.normalize_obs(loaded_env.venv.reset())
    action = model.predict(obs, deterministic=True)[0]
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], action, atol=1e-6)
    np.testing.assert_allclose(plain.predict(obs, deterministic=True)[0], action, atol=1e-6)
    loaded.learn(8 * 4, reset_num_timesteps=False)  # resumes on the device
    assert loaded.num_timesteps == 4 * 8 * 4 and isinstance(loaded.rollout_buffer, DeviceDictRolloutBuffer)


def test_with_any_other_env_it_is_sb3s_ppo(tmp_path):
    def single():
        return DummyVecEnv([lambda: gym.make("Unimal-FT-v0", morphologies=ROBOTS[:1], max_episode_steps=6)])

    kwargs = dict(n_steps=8, batch_size=8, n_epochs=1, seed=0, policy_kwargs=TINY)
    ref = first_rollout(PPO("MetaMorphPolicy", single(), **kwargs))
    buf = first_rollout(DevicePPO("MetaMorphPolicy", single(), **kwargs))
    assert type(buf) is DictRolloutBuffer
    for name in ("actions", "rewards", "values", "advantages"):
        np.testing.assert_array_equal(getattr(buf, name), getattr(ref, name), err_msg=name)
    # a model trained on the device path falls back too when loaded with another env
    on_device = DevicePPO("MetaMorphPolicy", batched(), **kwargs).learn(8 * 4)
    on_device.save(tmp_path / "model")
    elsewhere = DevicePPO.load(tmp_path / "model", env=single())
    assert type(elsewhere.rollout_buffer) is DictRolloutBuffer
    elsewhere.learn(8)


def test_frozen_observation_statistics_stay_frozen_on_the_device_and_unknown_wrappers_keep_sb3s_path():
    from stable_baselines3.common.vec_env import VecEnvWrapper

    from sb3_divmorph.algos.device_ppo import device_env_chain
    from sb3_divmorph.algos.finetune import freeze_observation_statistics

    venv = freeze_observation_statistics(batched())  # as transfer inherits a trained model's statistics
    frozen = {k: (venv.obs_rms[k].mean.copy(), venv.obs_rms[k].var.copy()) for k in NORM_KEYS}
    model = DevicePPO("MetaMorphPolicy", venv, n_steps=8, batch_size=32, n_epochs=1, seed=0, policy_kwargs=TINY)
    assert isinstance(first_rollout(model), DeviceDictRolloutBuffer)
    for key, (mean, var) in frozen.items():
        np.testing.assert_array_equal(venv.obs_rms[key].mean, mean)
        np.testing.assert_array_equal(venv.obs_rms[key].var, var)
    assert venv.ret_rms.count > 1, "the reward statistics still learn"

    class Custom(VecEnvWrapper):  # a wrapper DevicePPO does not know: SB3's VecEnv path, its semantics kept
        def reset(self):
            return self.venv.reset()

        def step_wait(self):
            return self.venv.step_wait()

    assert device_env_chain(Custom(batched())) is None


def test_a_transfer_on_the_batched_backend_runs_on_the_device_and_makes_the_vecenv_paths_update(tmp_path, monkeypatch):
    """``transfer.env_backend: batched``: the transfer run is a DevicePPO whose rollouts stay on the
    device, with the race's optimiser rules (selected tailors at the fine-tuning rate, learngenes
    slower, critic faster, frozen statistics) -- its update equals the one SB3's VecEnv path makes on
    the same batched env from the same student and seed; with a learning rate of 0 no weight moves."""
    import importlib

    transfer_module = importlib.import_module("divmorph.pipeline.transfer")  # the module, not the package's function
    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.files import mark_done
    from divmorph.pipeline.students import STUDENTS
    from divmorph.pipeline.transfer import transfer_run

    def profile(learning_rate: str = "lin_1e-3"):
        return load_profile(
            "demo",
            overrides={
                "train_robots": 2,
                "transfer.env_backend": "batched",
                "transfer.worlds_per_robot": 2,
                "transfer.n_timesteps": 32,
                "transfer.eval_every": 0,
                "transfer.checkpoint_every": 1000,
                "transfer.overrides": {"n_envs": 1, "n_steps": 8, "batch_size": 32, "n_epochs": 1},
                "transfer.finetune_overrides": {"learning_rate": learning_rate},
            },
        )

    def student_run(out):
        """A DivMorph student of the profile's size on FT, saved as the run's distilled student."""
        env = VecNormalize(DummyVecEnv([lambda: gym.make("Unimal-FT-v0", morphologies=ROBOTS)]), norm_obs_keys=["proprioceptive"])
        student = PPO("DivMorphPolicy", env, policy_kwargs=STUDENTS["divmorph"].kwargs(profile()), n_steps=8, batch_size=8, seed=1)
        student.learn(8)
        (out / "student").mkdir(parents=True)
        student.save(out / "student" / "model.zip")
        env.save(str(out / "student" / "vecnormalize.pkl"))
        mark_done(out / "student", num_timesteps=8)
        return student

    collected = []
    collect = DevicePPO._collect_on_device
    monkeypatch.setattr(DevicePPO, "_collect_on_device", lambda self, *a: collected.append(1) or collect(self, *a))
    student = student_run(tmp_path / "device")
    on_device = transfer_run(profile(), tmp_path / "device", "FT", "divmorph", calibration=True, progress_bar=False).run()
    assert isinstance(on_device, DevicePPO) and collected, "the transfer's rollouts were not collected on the device"

    student_run(tmp_path / "vecenv")
    monkeypatch.setattr(transfer_module, "DevicePPO", PPO)  # the same run through SB3's VecEnv path
    through_vecenv = transfer_run(profile(), tmp_path / "vecenv", "FT", "divmorph", calibration=True, progress_bar=False).run()
    assert type(through_vecenv) is PPO
    moved = False
    for (name, p), q in zip(through_vecenv.policy.named_parameters(), on_device.policy.parameters()):
        np.testing.assert_allclose(q.detach().numpy(), p.detach().numpy(), atol=1e-5, err_msg=name)
    for p, q in zip(student.policy.parameters(), on_device.policy.parameters()):
        moved |= not torch.allclose(p, q)
    assert moved, "the transfer trained nothing"

    monkeypatch.setattr(transfer_module, "DevicePPO", DevicePPO)
    student_run(tmp_path / "frozen")
    still = transfer_run(profile("lin_0"), tmp_path / "frozen", "FT", "divmorph", calibration=True, progress_bar=False).run()
    # (the transfer re-expresses the orthogonal factors, so compare what the policy does, not its parameters)
    env = gym.make("Unimal-FT-v0", morphologies=ROBOTS)
    obs = [env.reset(seed=k, options={"morphology": k % 2})[0] for k in range(4)]
    batch = still.get_vec_normalize_env().normalize_obs({key: np.stack([o[key] for o in obs]) for key in obs[0]})
    before, _ = student.predict(batch, deterministic=True)
    after, _ = still.predict(batch, deterministic=True)
    np.testing.assert_allclose(after, before, atol=1e-5, err_msg="an action changed with a learning rate of 0")


def _teachers(tmp_path):
    """Two tiny (random-init) MetaMorph teachers, FT and Patrol, each with its VecNormalize statistics."""
    from sb3_divmorph.algos.distillation import Teacher
    from unimal_envs.contract import TASK_NAMES

    found = {}
    for seed, task in enumerate(("FT", "Patrol")):
        venv = VecNormalize(
            DummyVecEnv([lambda task=task: gym.make(unimal_envs.env_id(task), morphologies=ROBOTS)]), norm_obs_keys=["proprioceptive"]
        )
        model = PPO("MetaMorphPolicy", venv, n_steps=16, batch_size=16, n_epochs=1, seed=seed, policy_kwargs=TINY)
        model.learn(16)
        model.save(tmp_path / task / "model.zip")
        venv.save(str(tmp_path / task / "vecnormalize.pkl"))
        found[TASK_NAMES.index(task)] = Teacher.load(tmp_path / task / "model.zip", tmp_path / task / "vecnormalize.pkl", task)
    return found


@pytest.mark.parametrize("beta", [0.0, 1.0])
def test_dagger_on_the_device_labels_stores_and_learns_what_the_vecenv_path_does(beta, tmp_path):
    """DAgger on the batched env: the states, the teachers' labels, the aggregated dataset and the
    student's distillation update are those of SB3's VecEnv path (TeacherMixingVecEnv in the chain
    keeps that path), with the dataset on the device; with beta = 1 every executed action is the
    teacher's (the same trajectory on both paths) while the buffer keeps the student's own."""
    from sb3_divmorph.algos.distillation import DAggerCallback, ImitationPPO, TeacherMixingVecEnv
    from unimal_envs.contract import TASK_NAMES

    teachers = _teachers(tmp_path)

    def env(mixed: bool):
        benv = make_batched_env(
            "MultiTask", morphologies=ROBOTS, worlds_per_robot=1, device="cpu", seed=0, max_episode_steps=5, tasks=["FT", "Patrol"]
        )
        inner = TeacherMixingVecEnv(benv, teachers, beta=beta, seed=0) if mixed else benv
        return VecNormalize(inner, norm_obs_keys=["proprioceptive"], norm_reward=False)

    runs = {}
    for path, mixed in (("vecenv", True), ("device", False)):
        student = ImitationPPO("DivMorphPolicy", env(mixed), n_steps=8, batch_size=64, seed=0, policy_kwargs=POLICIES["DivMorphPolicy"])
        dagger = DAggerCallback(teachers, TASK_NAMES, beta=beta, epochs=1, batch_size=16, buffer_size=256, seed=0)
        student.learn(8 * student.n_envs, callback=dagger)
        runs[path] = (student, dagger)
    (ref, ref_dagger), (dev, dev_dagger) = runs["vecenv"], runs["device"]
    assert ref_dagger._on_device is False and dev_dagger._on_device is True
    assert isinstance(dev_dagger.dataset.task, torch.Tensor) and isinstance(ref_dagger.dataset.task, np.ndarray)
    assert dev_dagger.dataset.size == ref_dagger.dataset.size == 8 * ref.n_envs
    for key, value in ref_dagger.dataset.obs.items():
        np.testing.assert_allclose(dev_dagger.dataset.obs[key].numpy(), value, atol=1e-5, err_msg=key)
    for name in ("mean", "std", "task"):
        np.testing.assert_allclose(getattr(dev_dagger.dataset, name).numpy(), getattr(ref_dagger.dataset, name), atol=1e-5, err_msg=name)
    for (name, p), q in zip(ref.policy.named_parameters(), dev.policy.parameters()):
        np.testing.assert_allclose(q.detach().numpy(), p.detach().numpy(), atol=1e-5, err_msg=name)
    if beta == 1.0:
        assert int(dev_dagger.teacher_steps) == 8 * dev.n_envs
        # the buffer holds the student's sampled actions, not the teachers' clipped means
        assert not np.allclose(
            dev.rollout_buffer.actions.numpy().reshape(8 * dev.n_envs, -1), ref_dagger.dataset.mean[: 8 * dev.n_envs], atol=1e-3
        )


def test_teachers_distillation_and_transfer_chain_on_the_batched_backend(tmp_path, monkeypatch):
    """The GPU path's stages, chained on CPU Warp at a tiny budget: teachers (DevicePPO), DAgger
    distillation into the DivMorph student (ImitationPPO on the device, teacher actions mixed in
    there) and its transfer to a novel task (DevicePPO with the race's rules), each on the batched
    backend, each leaving a finished stage the next one reads."""
    from sb3_divmorph.algos.distillation import ImitationPPO
    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.distill import distill
    from divmorph.pipeline.files import read_done
    from divmorph.pipeline.teachers import train_teachers
    from divmorph.pipeline.transfer import transfer

    batched_stage = {"env_backend": "batched", "worlds_per_robot": 1, "terrain_variants": 2}
    profile = load_profile(
        "demo",
        overrides={
            "train_robots": 2,
            "max_episode_steps": 20,
            "teachers.tasks": ["FT", "Patrol"],
            "teachers.n_timesteps": 32,
            "teachers.checkpoint_every": 1000,
            "teachers.overrides": {"n_envs": 1, "n_steps": 16, "batch_size": 32, "n_epochs": 1},
            **{f"teachers.{k}": v for k, v in batched_stage.items()},
            "distill.n_timesteps": 64,
            "distill.n_steps": 8,
            "distill.batch_size": 32,
            "distill.buffer_size": 128,
            "distill.checkpoint_every": 1000,
            **{f"distill.{k}": v for k, v in batched_stage.items()},
            "transfer.tasks": ["Escape"],
            "transfer.arms": ["divmorph"],
            "transfer.seeds": [0],
            "transfer.n_timesteps": 32,
            "transfer.eval_every": 0,
            "transfer.checkpoint_every": 1000,
            "transfer.overrides": {"n_envs": 1, "n_steps": 16, "batch_size": 32, "n_epochs": 1},
            **{f"transfer.{k}": v for k, v in batched_stage.items()},
        },
    )
    out = tmp_path / "run"
    on_device: dict[str, int] = {}
    collect = DevicePPO._collect_on_device
    monkeypatch.setattr(
        DevicePPO,
        "_collect_on_device",
        lambda self, *a: on_device.update({type(self).__name__: on_device.get(type(self).__name__, 0) + 1}) or collect(self, *a),
    )
    train_teachers(profile, out, progress_bar=False)
    assert on_device.pop("DevicePPO", 0) >= 2, "the teachers' rollouts were not on the device"
    distill(profile, out, progress_bar=False, students=["divmorph"])
    assert on_device.pop("ImitationPPO", 0) >= 1, "the distillation's rollouts were not on the device"
    transfer(profile, out, progress_bar=False)
    assert on_device.pop("DevicePPO", 0) >= 1, "the transfer's rollouts were not on the device"
    assert [read_done(out / "teachers" / t)["num_timesteps"] for t in ("FT", "Patrol")] == [32, 32]
    student = ImitationPPO.load(out / "student" / "model.zip", device="cpu")
    assert read_done(out / "student")["num_timesteps"] >= 64 and type(student.policy).__name__ == "DivMorphPolicy"
    assert read_done(out / "transfer" / "Escape" / "divmorph" / "seed-0")["num_timesteps"] >= 32
