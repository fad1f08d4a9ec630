"""DAgger distillation, transfer learning rates and the compact export, on tiny models."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import sb3_divmorph  # noqa: F401
import unimal_envs
from sb3_divmorph.algos.distillation import (
    DAggerCallback,
    DistillationDataset,
    ImitationPPO,
    SpaceMismatchError,
    Teacher,
    TeacherMixingVecEnv,
    gaussian_kl,
)
from sb3_divmorph.algos.finetune import UnitLearningRates, UnitSelection, prepare_transfer
from sb3_divmorph.deploy.compact import CompactActor, actor_inputs, export_torchscript
from sb3_divmorph.nn.layers import FactorizedLinear
from divmorph.pipeline.files import read_progress
from divmorph.pipeline.training import AtomicCheckpointCallback, TrainingRun, latest_checkpoint
from unimal_envs.contract import TASK_NAMES
from unimal_envs.morphology.loader import morphology_files
from unimal_envs.tasks import TASKS

TINY = dict(d_model=16, n_layers=1, ff_dim=32, exteroception=dict(hfield=[8], goal=[4], object=[4]))
TINY_DIVMORPH = dict(TINY, n_morph_tailors=6, n_task_tailors=6, top_k_morph=2, top_k_task=2)
ROBOTS = morphology_files("train")[:2]


def multitask_venv(n_envs=2, tasks=("FT", "Patrol"), mixer_teachers=None, beta=0.0):
    venv = DummyVecEnv([lambda: gym.make("Unimal-MultiTask-v1", tasks=list(tasks), morphologies=ROBOTS, max_episode_steps=50)] * n_envs)
    if mixer_teachers is not None:
        venv = TeacherMixingVecEnv(venv, mixer_teachers, beta=beta, seed=0)
    return VecNormalize(venv, norm_obs_keys=["proprioceptive"], norm_reward=False)


@pytest.fixture(scope="module")
def teachers(tmp_path_factory):
    """Two tiny (untrained, random-init) MetaMorph teachers saved with VecNormalize statistics."""
    folder = tmp_path_factory.mktemp("teachers")
    found = {}
    for seed, task in enumerate(("FT", "Patrol")):
        venv = VecNormalize(
            DummyVecEnv([lambda task=task: gym.make(unimal_envs.env_id(task), morphologies=ROBOTS, max_episode_steps=50)]),
            norm_obs_keys=["proprioceptive"],
        )
        model = PPO("MetaMorphPolicy", venv, n_steps=64, batch_size=64, n_epochs=1, seed=seed, policy_kwargs=TINY)
        model.learn(64)
        model.save(folder / task / "model.zip")
        venv.save(str(folder / task / "vecnormalize.pkl"))
        found[TASK_NAMES.index(task)] = Teacher.load(
            folder / task / "model.zip", folder / task / "vecnormalize.pkl", task, observation_space=venv.observation_space
        )
    return found


def test_gaussian_kl_is_scaled_squared_error_for_equal_std():
    t_mean, s_mean = th.tensor([[0.5, 1.0, 9.0]]), th.tensor([[0.0, 1.0, -9.0]])
    std = th.full((1, 3), 0.9)
    real = th.tensor([[True, True, False]])
    assert gaussian_kl(t_mean, std, s_mean, std, real).item() == pytest.approx(0.25 / (2 * 0.81), rel=1e-5)


def test_teacher_load_rejects_a_mismatched_observation_space(tmp_path):
    venv = DummyVecEnv([lambda: gym.make("Unimal-FT-v0", morphologies=ROBOTS)])
    PPO("MetaMorphPolicy", venv, n_steps=64, policy_kwargs=TINY).save(tmp_path / "t.zip")
    other = gym.spaces.Dict({**venv.observation_space.spaces, "proprioceptive": gym.spaces.Box(-1, 1, (12, 50))})
    with pytest.raises(SpaceMismatchError, match="proprioceptive"):
        Teacher.load(tmp_path / "t.zip", observation_space=other)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        Teacher.load(tmp_path / "missing.zip")


def test_dagger_reduces_the_kl_to_each_states_own_teacher(teachers):
    th.manual_seed(0)
    venv = multitask_venv()
    student = ImitationPPO("DivMorphPolicy", venv, n_steps=64, batch_size=64, seed=0, policy_kwargs=TINY_DIVMORPH)
    callback = DAggerCallback(teachers, TASK_NAMES, learning_rate=3e-3, epochs=4, batch_size=64, buffer_size=2000, seed=0)

    def kl_on(obs_raw):
        mean, std, tasks = callback.label(obs_raw)
        obs, _ = student.policy.obs_to_tensor(venv.normalize_obs(obs_raw))
        with th.no_grad():
            dist = student.policy.get_distribution(obs).distribution
        real = obs["act_padding_mask"] < 0.5
        return gaussian_kl(th.as_tensor(mean), th.as_tensor(std), dist.mean, dist.stddev, real).mean().item(), tasks

    callback.init_callback(student)
    before_params = [p.detach().clone() for p in student.policy.parameters()]
    student.learn(384, callback=callback)
    probe = {k: v[: callback.dataset.size] for k, v in callback.dataset.obs.items()}
    after, tasks = kl_on(probe)
    # the same states under the untrained student
    trained_state = {k: v.clone() for k, v in student.policy.state_dict().items()}
    for p, b in zip(student.policy.parameters(), before_params):
        p.data.copy_(b)
    before, _ = kl_on(probe)
    student.policy.load_state_dict(trained_state)
    assert set(np.unique(tasks)) == {TASK_NAMES.index("FT"), TASK_NAMES.index("Patrol")}
    assert after < 0.5 * before
    # ImitationPPO did not run PPO's update: the critic (not distilled) is untouched
    critic = [
        n for n, _ in student.policy.named_parameters() if n.startswith(("vf_features_extractor", "value_net", "mlp_extractor.value_net"))
    ]
    names = [n for n, _ in student.policy.named_parameters()]
    for name in critic:
        i = names.index(name)
        assert th.equal(before_params[i], dict(student.policy.named_parameters())[name].detach())


def test_a_saved_dagger_dataset_reloads_with_its_ring_position(tmp_path):
    rng = np.random.default_rng(0)
    dataset = DistillationDataset(10)

    def add(n):
        obs = {"a": rng.normal(size=(n, 3)).astype(np.float32), "task_index": rng.integers(0, 5, (n, 1)).astype(np.float32)}
        return obs, rng.normal(size=(n, 2)).astype(np.float32), rng.random((n, 2)).astype(np.float32), rng.integers(0, 5, n)

    for n in (4, 4, 5):  # 13 states into 10 slots: the ring has wrapped
        dataset.add(*add(n))
    dataset.save(tmp_path / "data.npz")
    reloaded = DistillationDataset.load(tmp_path / "data.npz", 10)
    batch = add(3)
    dataset.add(*batch)
    reloaded.add(*batch)  # the next states overwrite the same (oldest) rows in both
    assert (reloaded.size, reloaded._next) == (dataset.size, dataset._next) == (10, 6)
    for key in dataset.obs:
        np.testing.assert_array_equal(reloaded.obs[key], dataset.obs[key])
    for name in ("mean", "std", "task"):
        np.testing.assert_array_equal(getattr(reloaded, name), getattr(dataset, name))
    with pytest.raises(ValueError, match="capacity 10, expected 20"):
        DistillationDataset.load(tmp_path / "data.npz", 20)


def test_a_resumed_distillation_keeps_its_dataset_and_optimiser(teachers, tmp_path):
    """Checkpoints carry DAgger's aggregated dataset, optimiser and shuffling state into the resumed run."""

    def dagger():
        return DAggerCallback(teachers, TASK_NAMES, learning_rate=3e-3, epochs=1, batch_size=64, buffer_size=2000, seed=0)

    def make_model():
        return ImitationPPO("DivMorphPolicy", multitask_venv(), n_steps=64, batch_size=64, seed=0, policy_kwargs=TINY_DIVMORPH)

    # the first attempt: 2 rollouts of 2 envs x 64 steps, checkpointed at step 192 (during the
    # second rollout, so after one distillation round over 128 states), then "killed"
    first = dagger()
    checkpoints = tmp_path / "student" / "checkpoints"
    make_model().learn(256, callback=[first, AtomicCheckpointCallback(checkpoints, 192, [first])])
    saved = latest_checkpoint(checkpoints)
    assert saved.name.endswith("192")
    assert {p.name for p in saved.iterdir()} == {"dagger_dataset.npz", "dagger_state.pt", "model.zip", "vecnormalize.pkl"}

    resumed = dagger()
    TrainingRun(
        tmp_path / "student", 384, 1000, make_model, multitask_venv, algo=ImitationPPO, callbacks=[resumed], progress_bar=False
    ).run()
    # two more rollouts, each adding 128 states to the 128 aggregated before the checkpoint
    assert list(read_progress(tmp_path / "student")["distill/dataset_size"]) == [256, 384]
    # and Adam went on counting: 2 minibatches before the checkpoint, then 4 and 6
    assert int(resumed.optimizer.state_dict()["state"][0]["step"]) == 2 + 4 + 6


@pytest.mark.parametrize("load_balance", [0.0, 0.1])
def test_top1_gates_train_with_and_without_load_balancing_and_usage_is_logged(teachers, load_balance):
    th.manual_seed(0)
    venv = multitask_venv()
    kwargs = dict(TINY_DIVMORPH, top_k_morph=1, top_k_task=1)
    student = ImitationPPO("DivMorphPolicy", venv, n_steps=64, batch_size=64, seed=0, policy_kwargs=kwargs)
    callback = DAggerCallback(teachers, TASK_NAMES, learning_rate=3e-3, epochs=2, batch_size=64, seed=0, load_balance=load_balance)
    scorer = [p.detach().clone() for p in student.policy.router.morphology_gate.parameters()]
    student.learn(256, callback=callback)  # 2 envs x 64 steps: two distillation rounds
    moved = max((a - b.detach()).abs().max().item() for a, b in zip(scorer, student.policy.router.morphology_gate.parameters()))
    # top-1 weights are 1 in the forward pass, straight-through in the backward pass: the KL alone trains the scorer
    assert moved > 0
    assert len(callback.tailor_usage["morphology"]) == 2 and all(1 <= n <= 6 for n in callback.tailor_usage["morphology"])


def test_beta_one_executes_the_teachers_actions(teachers):
    venv = multitask_venv(n_envs=1, mixer_teachers=teachers, beta=1.0)
    mixer = venv.venv
    obs = venv.reset()
    raw = venv.get_original_obs()
    teacher = teachers[int(raw["task_index"][0, 0])]
    expected = teacher.act(raw)
    sent = {}
    original = mixer.venv.step_async
    mixer.venv.step_async = lambda actions: (sent.setdefault("a", actions.copy()), original(actions))[1]
    venv.step(np.zeros((1, 24), dtype=np.float32))
    np.testing.assert_allclose(sent["a"], expected)
    assert mixer.teacher_steps == 1
    del obs


def test_beta_without_a_mixer_or_with_ppo_is_refused(teachers):
    venv = multitask_venv(n_envs=1)
    student = ImitationPPO("DivMorphPolicy", venv, n_steps=32, batch_size=32, policy_kwargs=TINY_DIVMORPH)
    with pytest.raises(ValueError, match="TeacherMixingVecEnv"):
        student.learn(32, callback=DAggerCallback(teachers, TASK_NAMES, beta=0.5))
    venv = multitask_venv(n_envs=1, mixer_teachers=teachers)
    ppo = PPO("DivMorphPolicy", venv, n_steps=32, batch_size=32, policy_kwargs=TINY_DIVMORPH)
    with pytest.raises(ValueError, match="off-policy"):
        ppo.learn(32, callback=DAggerCallback(teachers, TASK_NAMES, beta=0.5))


def test_unit_learning_rates_scale_each_elements_update():
    p = th.nn.Parameter(th.zeros(2, 3))
    optimizer = th.optim.Adam([p], lr=0.1)
    UnitLearningRates(optimizer, {p: th.tensor([1.0, 0.1, 0.0])})
    p.grad = th.ones(2, 3)
    optimizer.step()
    np.testing.assert_allclose(p.detach().numpy(), [[-0.1, -0.01, 0.0]] * 2, rtol=1e-5)


def test_transfer_keeps_gates_fixed_and_unselected_tailors_frozen():
    th.manual_seed(0)
    venv = VecNormalize(
        DummyVecEnv([lambda: gym.make("Unimal-Escape-v0", morphologies=ROBOTS, max_episode_steps=50)]), norm_obs_keys=["proprioceptive"]
    )
    model = PPO("DivMorphPolicy", venv, n_steps=64, batch_size=64, n_epochs=2, learning_rate=1e-3, seed=0, policy_kwargs=TINY_DIVMORPH)
    obs = venv.reset()
    gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    assert 0 < selection.tailors.sum() < len(selection.tailors)
    prepare_transfer(model.policy, selection, learngene_scale=0.1)
    layer = next(m for m in model.policy.pi_features_extractor.modules() if isinstance(m, FactorizedLinear) and m.n_tailors)
    before_s = layer.singular_values.detach().clone()
    router_before = [p.detach().clone() for p in model.policy.router.parameters()]
    model.learn(128)
    moved = (layer.singular_values.detach() - before_s).abs()
    unselected = th.as_tensor(~selection.tailors)
    assert th.all(moved[layer.n_learngenes :][unselected] == 0)
    assert moved[layer.n_learngenes :][~unselected].max() > 0
    assert moved[: layer.n_learngenes].max() > 0
    assert all(th.equal(a, b) for a, b in zip(router_before, model.policy.router.parameters()))
    after = model.policy.get_gates(obs)
    assert th.equal(after.task, gates.task) and th.equal(after.morphology, gates.morphology)


@pytest.mark.parametrize("policy", ["DivMorphPolicy", "MetaMorphPolicy"])
def test_critic_warmup_trains_only_the_critic_then_both(policy):
    from sb3_divmorph.algos.finetune import CriticWarmup, critic_modules

    th.manual_seed(0)
    venv = VecNormalize(
        DummyVecEnv([lambda: gym.make("Unimal-Escape-v0", morphologies=ROBOTS, max_episode_steps=50)]), norm_obs_keys=["proprioceptive"]
    )
    model = PPO(
        policy,
        venv,
        n_steps=64,
        batch_size=64,
        n_epochs=2,
        learning_rate=1e-3,
        seed=0,
        policy_kwargs=TINY_DIVMORPH if policy == "DivMorphPolicy" else TINY,
    )
    if policy == "DivMorphPolicy":  # with the per-unit learning rates of a DivMorph transfer installed
        gates = model.policy.get_gates(venv.reset())
        prepare_transfer(model.policy, UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy()))
    critic = {id(p) for m in critic_modules(model.policy) for p in m.parameters()}

    def snapshot():
        return {name: p.detach().clone() for name, p in model.policy.named_parameters()}

    def moved(before, in_critic):
        return [n for n, p in model.policy.named_parameters() if (id(p) in critic) == in_critic and not th.equal(p.detach(), before[n])]

    warmup = CriticWarmup(128)
    before = snapshot()
    model.learn(128, callback=warmup)  # two updates, both inside the warm-up
    assert moved(before, in_critic=True) and not moved(before, in_critic=False)
    assert warmup.active
    before = snapshot()
    model.learn(64, callback=warmup, reset_num_timesteps=False)  # the update at 192 > 128 trains both
    assert moved(before, in_critic=True) and moved(before, in_critic=False)
    assert not warmup.active and all(
        p.requires_grad for p in model.policy.pi_features_extractor.parameters() if policy == "MetaMorphPolicy"
    )
    with pytest.raises(ValueError, match="critic warm-up"):
        CriticWarmup(-1)


@pytest.mark.parametrize("task, activation", [("FT", th.nn.ReLU), ("VT", th.nn.Tanh), ("ManipulateBox", th.nn.ReLU)])
def test_compact_actor_equals_the_student_and_runs_from_torch_alone(task, activation, tmp_path):
    th.manual_seed(1)
    venv = VecNormalize(
        DummyVecEnv([lambda: gym.make(unimal_envs.env_id(task), morphologies=ROBOTS[:1], max_episode_steps=50)]),
        norm_obs_keys=["proprioceptive"],
    )
    model = PPO(
        "DivMorphPolicy", venv, n_steps=64, batch_size=64, n_epochs=1, seed=0, policy_kwargs=dict(TINY_DIVMORPH, activation_fn=activation)
    )
    model.learn(64)  # moves the weights away from the SVD init and fills the statistics
    venv.training = False
    venv.reset()
    raw = [venv.get_original_obs()]
    for _ in range(6):
        venv.step(np.random.uniform(-1, 1, (1, 24)).astype(np.float32))
        raw.append(venv.get_original_obs())
    batch = {k: np.concatenate([r[k] for r in raw]) for k in raw[0]}
    first = {k: v[0] for k, v in batch.items()}
    actor = CompactActor.from_policy(model.policy, first, TASKS[task].observation_keys, venv)
    obs_t, _ = model.policy.obs_to_tensor(venv.normalize_obs(batch))
    with th.no_grad():
        reference = model.policy.get_distribution(obs_t).distribution.mean
        got = actor(*actor_inputs(batch, batch=True))
    assert (reference - got).abs().max().item() <= 1e-5
    assert th.all(got[:, batch["act_padding_mask"][0] > 0.5] == 0)
    assert actor.stored_numbers()["weights"] < sum(p.numel() for p in model.policy.parameters()) / 2

    path = export_torchscript(actor, first, tmp_path / "actor.pt", {"task": task})
    np.savez(tmp_path / "inputs.npz", reference=reference.numpy(), **{k: batch[k] for k in ("proprioceptive", "hfield", "goal", "object")})
    script = (
        "import sys, numpy as np, torch\n"
        "d = np.load(sys.argv[2]); actor = torch.jit.load(sys.argv[1])\n"
        "out = actor(*(torch.as_tensor(d[k]) for k in ('proprioceptive', 'hfield', 'goal', 'object')))\n"
        "assert 'sb3_divmorph' not in sys.modules and 'stable_baselines3' not in sys.modules\n"
        "print(float((out - torch.as_tensor(d['reference'])).abs().max()))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script, str(path), str(tmp_path / "inputs.npz")], capture_output=True, text=True, check=True
    )
    assert float(result.stdout.strip()) <= 1e-5


def test_bounded_targets_adamw_and_a_distilled_critic_are_recipe_options(teachers):
    """DAgger's recipe options (issue 42): ``target_bound`` clips the teachers' means before they
    become targets (a teacher asking for 50 where the env clips at 1 gets 1); ``optimizer="adamw"``
    decays the weights; ``value_weight`` trains the student's critic toward each state's own teacher
    critic (without it, distillation leaves the critic as initialised)."""
    import copy

    steep = {k: copy.copy(t) for k, t in teachers.items()}
    for teacher in steep.values():  # the same teachers with their action means scaled up 50x
        teacher.policy = copy.deepcopy(teacher.policy)
        with th.no_grad():
            for p in teacher.policy.action_net.parameters():
                p.mul_(50.0)

    def run(**options):
        venv = multitask_venv()
        student = ImitationPPO("DivMorphPolicy", venv, n_steps=32, batch_size=64, seed=0, policy_kwargs=TINY_DIVMORPH)
        callback = DAggerCallback(steep, TASK_NAMES, learning_rate=3e-3, epochs=3, batch_size=64, buffer_size=1000, seed=0, **options)
        student.learn(192, callback=callback)
        return student, callback

    _, unbounded = run()
    assert np.abs(unbounded.dataset.mean[: unbounded.dataset.size]).max() > 2.0
    _, bounded = run(target_bound=1.0)
    assert np.abs(bounded.dataset.mean[: bounded.dataset.size]).max() <= 1.0

    _, decayed = run(optimizer="adamw", weight_decay=0.03)
    assert isinstance(decayed.optimizer, th.optim.AdamW) and decayed.optimizer.param_groups[0]["weight_decay"] == 0.03

    def value_error(student, callback):
        rows = np.arange(callback.dataset.size)
        raw = {k: v[rows] for k, v in callback.dataset.obs.items()}
        target = callback.dataset.value[rows] if callback.dataset.value is not None else None
        if target is None:
            from sb3_divmorph.algos.distillation import teacher_values

            target = teacher_values(steep, raw, callback.dataset.task[rows])
        obs, _ = student.policy.obs_to_tensor(student.get_vec_normalize_env().normalize_obs(raw))
        with th.no_grad():
            values = student.policy.predict_values(obs).flatten().numpy()
        return float(np.mean((values - target) ** 2))

    plain_student, plain = run()
    critic_student, with_critic = run(value_weight=1.0)
    assert with_critic.dataset.value is not None and plain.dataset.value is None
    assert value_error(critic_student, with_critic) < 0.5 * value_error(plain_student, plain)
