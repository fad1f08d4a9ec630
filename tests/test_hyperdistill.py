"""HyperDistill: imitation from a fixed teacher, DAgger, per-robot MLP export (TorchScript, ONNX), bad input, pipeline."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import sb3_divmorph  # noqa: F401
from sb3_divmorph.algos.distillation import DAggerCallback, ImitationPPO, SpaceMismatchError, Teacher
from sb3_divmorph.algos.hyperdistill_fit import TeacherRollouts, collect_teacher_rollouts, distillation_loss, fit_offline, load_student
from sb3_divmorph.deploy.compact import actor_inputs, export_torchscript
from sb3_divmorph.deploy.deployment import export_onnx
from sb3_divmorph.deploy.hyperdistill_mlp import HyperDistillMLP
from sb3_divmorph.policies.hyperdistill import HyperDistillPolicy
import unimal_envs
from unimal_envs import contract
from unimal_envs.contract import TASK_NAMES
from unimal_envs.morphology.loader import morphology_files
from unimal_envs.tasks import TASKS

th.set_num_threads(1)
ROBOTS = morphology_files("train")[:3]
STUDENT = dict(hidden_dim=32, n_layers=2, embed_dim=16, encoder_ff_dim=32, exteroception=dict(hfield=[8], goal=[4], object=[4]))
TEACHER = dict(d_model=16, n_layers=1, ff_dim=32, hypernet_dim=8, net_arch=dict(pi=[16], vf=[16]), exteroception={})


def multitask_venv(n_envs=2, tasks=("FT",)):
    venv = DummyVecEnv([lambda: gym.make("Unimal-MultiTask-v1", tasks=list(tasks), morphologies=ROBOTS, max_episode_steps=60)] * n_envs)
    venv.seed(0)
    return VecNormalize(venv, norm_obs_keys=["proprioceptive"], norm_reward=False)


@pytest.fixture(scope="module")
def teacher():
    """A fixed, non-trivial ModuMorph teacher: random weights scaled so its action means are O(0.5)
    and depend on the state and on the robot."""
    th.manual_seed(3)
    policy = ModuMorph = sb3_divmorph.ModuMorphPolicy(contract.observation_space(), contract.action_space(), lambda _: 0.0, **TEACHER)
    g = th.Generator().manual_seed(3)
    with th.no_grad():
        for p in ModuMorph.parameters():
            p.add_(th.randn(p.shape, generator=g) * 0.12)
    policy.set_training_mode(False)
    # the teacher's own observation normalisation, as a trained teacher would have
    normalizer = multitask_venv(tasks=("FT", "VT", "ManipulateBox"))
    normalizer.reset()
    for _ in range(100):
        normalizer.step(np.random.default_rng(0).uniform(-1, 1, (2, 24)).astype(np.float32))
    normalizer.training = False
    return {TASK_NAMES.index("FT"): Teacher(policy, normalizer, "FT")}


def imitation_error(policy, dataset, normalizer) -> float:
    obs, _ = policy.obs_to_tensor(normalizer.normalize_obs({k: v[: dataset.size] for k, v in dataset.obs.items()}))
    with th.no_grad():
        mean = policy.get_distribution(obs).distribution.mean
    real = obs["act_padding_mask"] < 0.5
    return float((mean - th.as_tensor(dataset.mean[: dataset.size])).abs()[real].mean())


# NLL fits the teacher's *sampled* actions (std 0.9 noise around the means): on 600 states the
# student partly fits that noise, so its error to the teacher's means falls less than with the KL.
@pytest.mark.parametrize("loss, fraction", [("kl", 0.25), ("nll", 0.4)])
def test_offline_imitation_error_falls_to_a_small_fraction(teacher, loss, fraction):
    venv = multitask_venv()
    dataset = collect_teacher_rollouts(teacher, venv, 600, seed=0)
    assert dataset.size == 600 and len({tuple(c.ravel()) for c in dataset.obs["context"]}) >= 2  # several robots
    teacher_scale = float(np.abs(dataset.mean[dataset.obs["act_padding_mask"] < 0.5]).mean())
    assert 0.2 < teacher_scale < 5  # the teacher is not trivially ~0, nor degenerate
    th.manual_seed(0)
    student = HyperDistillPolicy(venv.observation_space, venv.action_space, lambda _: 0.0, **STUDENT)
    before = imitation_error(student, dataset, venv)
    history = fit_offline(student, dataset, venv, loss=loss, epochs=60, batch_size=150, learning_rate=3e-3)
    after = imitation_error(student, dataset, venv)
    assert history[-1] < history[0]
    assert after < fraction * before, (before, after)


def test_a_killed_offline_fit_resumes_to_the_student_of_an_uninterrupted_one(teacher, tmp_path):
    venv = multitask_venv()
    dataset = collect_teacher_rollouts(teacher, venv, 96, seed=0)
    # the stage keeps its states on disk: they read back whole, the teacher's sampled actions included
    dataset.save(tmp_path / "rollouts.npz")
    loaded = TeacherRollouts.load(tmp_path / "rollouts.npz")
    for name in ("mean", "std", "task", "actions"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(dataset, name))
    np.testing.assert_array_equal(loaded.obs["proprioceptive"], dataset.obs["proprioceptive"])

    def student():
        th.manual_seed(0)
        return HyperDistillPolicy(venv.observation_space, venv.action_space, lambda _: 0.0, **STUDENT)

    settings = dict(loss="nll", batch_size=32, learning_rate=3e-3, seed=5)
    whole = student()
    expected = fit_offline(whole, dataset, venv, epochs=3, **settings)
    checkpoint = tmp_path / "offline-fit.pt"
    fit_offline(student(), dataset, venv, epochs=1, checkpoint=checkpoint, **settings)  # killed after epoch 1
    resumed = student()  # a fresh process: the initial weights again, then the checkpoint
    assert fit_offline(resumed, loaded, venv, epochs=3, checkpoint=checkpoint, **settings) == expected
    for a, b in zip(whole.parameters(), resumed.parameters()):
        assert th.equal(a, b)


def test_dagger_trains_the_student(teacher):
    venv = multitask_venv()
    th.manual_seed(0)
    model = ImitationPPO("HyperDistillPolicy", venv, n_steps=64, batch_size=64, seed=0, policy_kwargs=STUDENT)
    callback = DAggerCallback(teacher, TASK_NAMES, learning_rate=3e-3, epochs=6, batch_size=64, buffer_size=2000, seed=0)
    callback.init_callback(model)
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.learn(384, callback=callback)
    probe = {k: v[: callback.dataset.size] for k, v in callback.dataset.obs.items()}
    mean, std, _ = callback.label(probe)
    obs, _ = model.policy.obs_to_tensor(venv.normalize_obs(probe))

    def kl() -> float:
        with th.no_grad():
            return float(distillation_loss(model.policy, obs, th.as_tensor(mean), th.as_tensor(std), None, "kl"))

    after_kl = kl()
    trained = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.policy.load_state_dict(before)
    assert after_kl < 0.5 * kl()
    model.policy.load_state_dict(trained)


@pytest.fixture(scope="module")
def trained_student(teacher):
    tasks = ("FT", "VT", "ManipulateBox")  # statistics of the tasks it is exported for
    venv = multitask_venv(tasks=tasks)
    one = next(iter(teacher.values()))
    dataset = collect_teacher_rollouts({TASK_NAMES.index(t): one for t in tasks}, venv, 600, seed=1)
    th.manual_seed(1)
    student = HyperDistillPolicy(venv.observation_space, venv.action_space, lambda _: 0.0, **STUDENT)
    fit_offline(student, dataset, venv, epochs=3, batch_size=200, learning_rate=3e-3)
    with th.no_grad():  # move the generators off zero so each robot's MLP differs (the raw height
        # map of VT is large, so its encoder, trained on FT's zeros only, is scaled down to keep means O(1))
        for name, p in student.named_parameters():
            p.add_(th.randn_like(p) * 0.01) if "exteroception" not in name else p.mul_(0.01)
    venv.training = False
    return student, venv


@pytest.mark.parametrize("task", ["VT", "ManipulateBox"])
def test_exported_mlp_equals_the_student_and_onnx_runs_without_torch(trained_student, task, tmp_path):
    student, normalizer = trained_student
    env = gym.make(unimal_envs.env_id(task), morphologies=ROBOTS[1:2], max_episode_steps=50)
    obs, _ = env.reset(seed=0)
    observations = [obs]
    for _ in range(7):
        obs, *_ = env.step(env.action_space.sample())
        observations.append(obs)
    batch = {k: np.stack([o[k] for o in observations]) for k in obs}
    first = {k: v[0] for k, v in batch.items()}
    mlp = HyperDistillMLP.from_policy(student, first, TASKS[task].observation_keys, normalizer)
    with th.no_grad():
        reference = student.get_distribution(student.obs_to_tensor(normalizer.normalize_obs(batch))[0]).distribution.mean
        got = mlp(*actor_inputs(batch, batch=True))
    assert 0.05 < reference.abs().max() < 20  # realistic action means, not a degenerate 0
    assert (reference - got).abs().max() <= 1e-5
    assert th.all(got[:, batch["act_padding_mask"][0] > 0.5] == 0)
    # a plain MLP: Linear layers only, no context encoder or generator, far smaller than the student
    assert not any(n.startswith(("encoders", "in_weight", "hidden_weight", "out_weight")) for n, _ in mlp.named_parameters())
    assert mlp.stored_numbers()["weights"] < student.parameter_counts()["total"] / 2
    # another robot gets another MLP
    other = HyperDistillMLP.from_policy(
        student,
        {**first, **{k: v for k, v in _robot_obs(task, 2).items() if k in ("context", "obs_padding_mask", "act_padding_mask")}},
        TASKS[task].observation_keys,
        normalizer,
    )
    assert not th.allclose(other(*actor_inputs(first)), mlp(*actor_inputs(first)))

    path = export_torchscript(mlp, first, tmp_path / "mlp.pt", {"task": task})
    assert (th.jit.load(str(path))(*actor_inputs(batch, batch=True)) - reference).abs().max() <= 1e-5
    onnx_path = export_onnx(mlp, first, tmp_path / "mlp.onnx", {"task": task})
    np.savez(tmp_path / "inputs.npz", reference=reference.numpy(), **{k: batch[k] for k in ("proprioceptive", "hfield", "goal", "object")})
    script = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('torch', 'sb3_divmorph', 'stable_baselines3', 'unimal_envs'):\n"
        "            raise ImportError('blocked: ' + name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import numpy as np, onnxruntime as ort\n"
        "d = np.load(sys.argv[2]); s = ort.InferenceSession(sys.argv[1], providers=['CPUExecutionProvider'])\n"
        "names = [i.name for i in s.get_inputs()]\n"
        "assert set(names) <= {'proprioceptive', 'hfield', 'goal', 'object'} and 'proprioceptive' in names\n"
        "out = s.run(['actions'], {k: d[k] for k in names})[0]\n"
        "assert not any(m.split('.')[0] == 'torch' for m in sys.modules)\n"
        "print(float(np.abs(out - d['reference']).max()))\n"
    )
    result = subprocess.run([sys.executable, "-c", script, str(onnx_path), str(tmp_path / "inputs.npz")], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert float(result.stdout.strip()) <= 1e-5


def _robot_obs(task: str, index: int) -> dict[str, np.ndarray]:
    env = gym.make(unimal_envs.env_id(task), morphologies=ROBOTS[index : index + 1], max_episode_steps=10)
    return env.reset(seed=0)[0]


def test_bad_input_gives_clear_errors(trained_student, tmp_path):
    student, normalizer = trained_student
    obs = _robot_obs("FT", 0)
    too_many = {
        **obs,
        "context": np.zeros((13, obs["context"].shape[1]), np.float32),
        "proprioceptive": np.zeros((13, obs["proprioceptive"].shape[1]), np.float32),
    }
    with pytest.raises(ValueError, match="13 tokens.*at most 12"):
        HyperDistillMLP.from_policy(student, too_many, ("hfield",), normalizer)
    batch = {k: th.as_tensor(v[None]) for k, v in too_many.items()}
    with pytest.raises(ValueError, match="at most 12"):
        student.network(batch)
    with pytest.raises(ValueError, match="unknown distillation loss 'mse'"):
        fit_offline(student, None, loss="mse")  # type: ignore[arg-type]
    # a checkpoint used with another observation space
    model = ImitationPPO("HyperDistillPolicy", multitask_venv(n_envs=1), n_steps=16, batch_size=16, policy_kwargs=STUDENT)
    model.save(tmp_path / "student.zip")
    assert isinstance(load_student(tmp_path / "student.zip", model.observation_space), HyperDistillPolicy)
    other = gym.spaces.Dict({**model.observation_space.spaces, "proprioceptive": gym.spaces.Box(-1, 1, (12, 50))})
    with pytest.raises(SpaceMismatchError, match="proprioceptive"):
        load_student(tmp_path / "student.zip", other)
    PPO("MetaMorphPolicy", multitask_venv(n_envs=1), n_steps=16, policy_kwargs=dict(d_model=8, n_layers=1, ff_dim=8)).save(
        tmp_path / "meta.zip"
    )
    with pytest.raises(TypeError, match="not a HyperDistill student"):
        load_student(tmp_path / "meta.zip")


def _hyperdistill_profile() -> dict:
    """The tiny pipeline profile with a HyperDistill stage (one task, ModuMorph teachers of 64 steps)."""
    from test_pipeline import TINY

    profile = json.loads(json.dumps(TINY))
    profile["teachers"].update(tasks=["FT"], n_timesteps=64, policy_kwargs=dict(TINY["teachers"]["policy_kwargs"], hypernet_dim=8))
    profile["export"] = {"tasks": ["FT"], "robots_per_split": 1, "latency_repeats": 3}
    profile["hyperdistill"] = {
        "policy_kwargs": STUDENT,
        "rollout_samples": 128,
        "epochs": 30,
        "batch_size": 64,
        "learning_rate": 0.003,
        "dagger_timesteps": 64,
        "n_envs": 2,
        "n_steps": 32,
        "buffer_size": 256,
    }
    return profile


def test_pipeline_trains_modumorph_teachers_distils_and_exports(tmp_path):
    from test_pipeline import write_profiles

    from divmorph.cli import main as cli
    from divmorph.pipeline.config import ConfigError, load_profile

    profile = _hyperdistill_profile()
    path = tmp_path / "profiles.yml"
    path.write_text(yaml.safe_dump({"tiny": profile}))
    out = tmp_path / "run"
    assert cli(["hyperdistill", "--profile", "tiny", "--profiles", str(path), "--out", str(out), "--no-progress"]) == 0
    # the run's teachers are MetaMorph (zoo default), so ModuMorph teachers were trained for HyperDistill
    teacher = PPO.load(out / "hyperdistill" / "teachers" / "FT" / "model.zip", device="cpu")
    assert type(teacher.policy).__name__ == "ModuMorphPolicy"
    assert not (out / "teachers" / "FT").exists()
    reports = [json.loads(p.read_text()) for p in (out / "hyperdistill" / "export").glob("*/report.json")]
    assert len(reports) == 2 and all(r["max_abs_diff"] <= 1e-5 and r["mlp_weights"] > 0 for r in reports)
    assert all((p / "mlp.pt").is_file() and (p / "mlp.onnx").is_file() for p in (out / "hyperdistill" / "export").iterdir())
    # the resume files (the states, the fit's checkpoint) are gone once the student is saved
    assert sorted(p.name for p in (out / "hyperdistill" / "student").iterdir()) == ["done.json", "logs", "model.zip"]
    student = load_student(out / "hyperdistill" / "student" / "model.zip")
    assert student.task_input == "index" and student.observation_statistics == "teachers"  # the profile's defaults
    # the student normalises FT's states with the FT teacher's statistics (no normaliser of its own)
    from sb3_divmorph.algos.distillation import load_normalizer

    assert not (out / "hyperdistill" / "student" / "vecnormalize.pkl").exists()
    teacher_stats = load_normalizer(out / "hyperdistill" / "teachers" / "FT" / "vecnormalize.pkl")
    raw = {k: v[None] for k, v in _robot_obs("FT", 0).items()}
    ours = student.normalize_with_teachers(student.obs_to_tensor(raw)[0])["proprioceptive"].numpy()
    assert np.abs(ours - teacher_stats.normalize_obs(raw)["proprioceptive"]).max() <= 1e-6
    # written per task from its teachers: no MLP for a task without a teacher
    from divmorph.pipeline.hyperdistill import export_mlp

    with pytest.raises(ConfigError, match="no teacher for 'Escape'"):
        export_mlp(load_profile("tiny", path), out, ROBOTS[0], "Escape")
    # teachers.policy picks the run's teachers' policy; unknown names are refused, naming the choices
    profile["teachers"]["policy"] = "ModuMorphPolicy"
    path.write_text(yaml.safe_dump({"tiny": profile}))
    from divmorph.pipeline.teachers import teacher_run

    run = teacher_run(load_profile("tiny", path), tmp_path / "other", "FT", progress_bar=False)
    assert type(run.make_model().policy).__name__ == "ModuMorphPolicy"
    for where in ("teachers", "hyperdistill"):
        bad = json.loads(json.dumps(profile))
        bad[where]["teacher_policy" if where == "hyperdistill" else "policy"] = "TransformerPolicy"
        path.write_text(yaml.safe_dump({"tiny": bad}))
        with pytest.raises(ConfigError, match="unknown teacher policy 'TransformerPolicy'.*ModuMorphPolicy"):
            load_profile("tiny", path)
    del write_profiles


def _random_modumorph(seed: int):
    th.manual_seed(seed)
    policy = sb3_divmorph.ModuMorphPolicy(contract.observation_space(), contract.action_space(), lambda _: 0.0, **TEACHER)
    g = th.Generator().manual_seed(seed)
    with th.no_grad():
        for p in policy.parameters():
            p.add_(th.randn(p.shape, generator=g) * 0.12)
    policy.set_training_mode(False)
    return policy


def test_task_input_lets_one_student_tell_ft_from_incline(teacher):
    """FT and Incline share their observation keys: on the same states, labelled by two teachers
    that act differently, the student with the task index as input imitates both, the one without
    it can only average them."""
    from sb3_divmorph.algos.distillation import teacher_labels
    from sb3_divmorph.algos.hyperdistill_fit import TeacherRollouts

    ft = next(iter(teacher.values()))
    incline = TASK_NAMES.index("Incline")
    teachers = {TASK_NAMES.index("FT"): ft, incline: Teacher(_random_modumorph(11), ft.normalizer, "Incline")}
    venv = multitask_venv()
    states = collect_teacher_rollouts(teacher, venv, 300, seed=0).obs
    dataset = TeacherRollouts(600)
    for task in ("FT", "Incline"):
        obs = {**states, "task_index": np.full_like(states["task_index"], TASK_NAMES.index(task))}
        mean, std, tasks = teacher_labels(teachers, obs, 24)
        dataset.add_with_actions(obs, mean, std, tasks, mean)
    errors, students = {}, {}
    for task_input in ("none", "index"):
        th.manual_seed(0)
        student = HyperDistillPolicy(venv.observation_space, venv.action_space, lambda _: 0.0, task_input=task_input, **STUDENT)
        fit_offline(student, dataset, venv, loss="kl", epochs=60, batch_size=150, learning_rate=3e-3)
        errors[task_input], students[task_input] = imitation_error(student, dataset, venv), student
    assert errors["index"] < 0.6 * errors["none"], errors
    # one state read as FT and as Incline: the task-conditioned student acts as each task's teacher
    as_task = {t: {k: v[300:301] if t == "Incline" else v[:1] for k, v in dataset.obs.items()} for t in ("FT", "Incline")}
    real = as_task["FT"]["act_padding_mask"][0] < 0.5

    def means(policy, obs):
        with th.no_grad():
            return policy.get_distribution(policy.obs_to_tensor(venv.normalize_obs(obs))[0]).distribution.mean[0].numpy()[real]

    teacher_gap = np.abs(dataset.mean[300][real] - dataset.mean[0][real]).mean()
    student_gap = np.abs(means(students["index"], as_task["Incline"]) - means(students["index"], as_task["FT"])).mean()
    assert teacher_gap > 0.2 and student_gap > 0.5 * teacher_gap, (teacher_gap, student_gap)
    assert np.array_equal(means(students["none"], as_task["Incline"]), means(students["none"], as_task["FT"]))
    # the exported MLP is the one of the robot doing that task
    first = {k: v[0] for k, v in as_task["Incline"].items()}
    mlp = HyperDistillMLP.from_policy(students["index"], first, TASKS["Incline"].observation_keys, venv)
    with th.no_grad():
        assert np.abs(mlp(*actor_inputs(first))[0].numpy()[real] - means(students["index"], as_task["Incline"])).max() <= 1e-5
    with pytest.raises(ValueError, match="task_input must be one of"):
        HyperDistillPolicy(venv.observation_space, venv.action_space, lambda _: 0.0, task_input="embedding", **STUDENT)


@pytest.mark.shipped_results
def test_the_small_runs_record_says_its_hyperdistill_ran_under_the_retired_rules(archived_study):
    """results/cpu's student was trained without a task input, on statistics of its own: its record
    (archived with the run), migrated to today's keys, keeps both as retired rules."""
    record = json.loads((archived_study("results/cpu") / "run.json").read_text())
    assert {k: v for k, v in record["retired"].items() if k.startswith("hyperdistill.")} == {
        "hyperdistill.task_input": "none",
        "hyperdistill.observation_statistics": "own",
    }


def test_a_student_is_always_told_its_task_and_one_trained_before_that_loads_as_it_was(tmp_path):
    """The pipeline's student reads the task's index and its teachers' statistics: the profile keys
    that once chose otherwise are errors naming what replaced them, a record of a run made under them
    migrates to the retired rules, and a student saved before the keys existed loads as trained."""
    from test_pipeline import TINY

    from divmorph.pipeline.config import ConfigError, load_profile
    from divmorph.pipeline.provenance import configuration
    from divmorph.pipeline.retired import migrate_record

    profile = json.loads(json.dumps(TINY))
    profile["hyperdistill"] = {"policy_kwargs": STUDENT}
    path = tmp_path / "profiles.yml"
    path.write_text(yaml.safe_dump({"tiny": profile}))
    new = load_profile("tiny", path)
    for bad, message in (
        ({"task_input": "index"}, "hyperdistill.task_input was removed in divmorph 0.2: it always runs 'index'"),
        ({"policy_kwargs": dict(STUDENT, task_input="none")}, "policy_kwargs.task_input is set by the pipeline"),
        ({"observation_statistics": "own"}, "hyperdistill.observation_statistics was removed in divmorph 0.2"),
    ):
        path.write_text(yaml.safe_dump({"tiny": {**profile, "hyperdistill": {**profile["hyperdistill"], **bad}}}))
        with pytest.raises(ConfigError, match=message):
            load_profile("tiny", path)
    # a record from before the keys: its hyperdistill section lacks them, so it ran the former rules
    migrated, changes = migrate_record({"configuration": configuration(new), "history": []})
    retired = {key: value for key, value in migrated["retired"].items() if key.startswith("hyperdistill.")}
    assert retired == {"hyperdistill.task_input": "none", "hyperdistill.observation_statistics": "own"}
    assert migrated["configuration"]["hyperdistill"] == configuration(new)["hyperdistill"]
    assert "hyperdistill.task_input: 'none' (retired: today's rule is 'index')" in changes
    # a student saved before the keys existed (its saved policy_kwargs lack them) loads as it was
    # trained; results/cpu's own such student left the tree (git history), so one is made here
    legacy = PPO(HyperDistillPolicy, multitask_venv(tasks=("FT",)), policy_kwargs=STUDENT, n_steps=16, batch_size=16, device="cpu")
    assert "task_input" not in legacy.policy_kwargs
    legacy.save(tmp_path / "legacy.zip")
    shipped = load_student(tmp_path / "legacy.zip")
    assert (shipped.task_input, shipped.observation_statistics) == ("none", "own")
    assert shipped.network.context_dim == contract.observation_space()["context"].shape[1]


def test_student_on_its_teachers_statistics_sees_what_each_teacher_sees(teacher, tmp_path):
    """``observation_statistics="teachers"``: raw observations in, each state normalised with the
    statistics of its own task's teacher (as the teacher does), kept through save / load and baked
    into the exported MLP; a state of a task without a teacher is refused."""
    ft = next(iter(teacher.values()))
    venv = multitask_venv(n_envs=1)
    model = ImitationPPO(
        "HyperDistillPolicy",
        venv,
        n_steps=16,
        batch_size=16,
        policy_kwargs=dict(STUDENT, task_input="index", observation_statistics="teachers"),
    )
    model.policy.set_teacher_statistics(TASK_NAMES.index("FT"), ft.normalizer)
    th.manual_seed(0)
    with th.no_grad():
        for p in model.policy.parameters():
            p.add_(th.randn_like(p) * 0.02)
    model.save(tmp_path / "student.zip")
    student = load_student(tmp_path / "student.zip")
    raw = {k: v[None] for k, v in _robot_obs("FT", 1).items()}
    obs = student.obs_to_tensor(raw)[0]
    ours = student.normalize_with_teachers(obs)["proprioceptive"].numpy()
    theirs = ft.normalizer.normalize_obs(raw)["proprioceptive"]
    assert np.abs(ours - theirs).max() <= 1e-6 and np.abs(theirs - raw["proprioceptive"]).max() > 0.5  # not the identity
    # the same weights fed the teacher-normalised state acts the same
    own = HyperDistillPolicy(venv.observation_space, venv.action_space, lambda _: 0.0, task_input="index", **STUDENT)
    own.load_state_dict({k: v for k, v in student.state_dict().items() if not k.startswith("teacher_")})
    with th.no_grad():
        mean = student.get_distribution(obs).distribution.mean
        assert th.allclose(mean, own.get_distribution(own.obs_to_tensor(ft.normalizer.normalize_obs(raw))[0]).distribution.mean, atol=1e-5)
        mlp = HyperDistillMLP.from_policy(student, {k: v[0] for k, v in raw.items()}, TASKS["FT"].observation_keys)
        assert (mlp(*actor_inputs({k: v[0] for k, v in raw.items()})) - mean).abs().max() <= 1e-5
    with pytest.raises(ValueError, match=r"no teacher statistics for task index\(es\) \[2\]"):
        student.get_distribution({**obs, "task_index": th.full_like(obs["task_index"], TASK_NAMES.index("Incline"))})
    with pytest.raises(ValueError, match="observation_statistics must be one of"):
        HyperDistillPolicy(venv.observation_space, venv.action_space, lambda _: 0.0, observation_statistics="student", **STUDENT)


def test_a_stage_killed_in_its_offline_fit_reads_its_states_back(tmp_path, monkeypatch, capsys):
    stage = importlib.import_module("divmorph.pipeline.hyperdistill")  # the package re-exports a function of that name
    from divmorph.pipeline.config import load_profile

    path = tmp_path / "profiles.yml"
    path.write_text(yaml.safe_dump({"tiny": _hyperdistill_profile()}))
    profile, out = load_profile("tiny", path), tmp_path / "run"

    class Killed(Exception):
        pass

    def killed(*args, **kwargs):
        raise Killed

    with monkeypatch.context() as patch:
        patch.setattr(stage, "fit_offline", killed)
        with pytest.raises(Killed):
            stage.train_student(profile, out, progress_bar=False)
    assert (out / "hyperdistill" / "student" / stage.ROLLOUTS).is_file()
    monkeypatch.setattr(stage, "collect_teacher_rollouts", killed)  # a second collection would fail the test
    folder = stage.train_student(profile, out, progress_bar=False)
    assert "128 teacher-rollout states read from rollouts.npz" in capsys.readouterr().out
    assert (folder / "model.zip").is_file() and not (folder / stage.ROLLOUTS).exists()
