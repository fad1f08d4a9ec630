"""Everyday paths of a researcher: clear messages, quiet bars when asked, shared files, the tour's
picture, ``divmorph record``, rl-zoo's extras, and the on-policy algorithms the policies serve."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import tomllib
import yaml
from stable_baselines3 import A2C, PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

import unimal_envs
from divmorph.cli import main as cli
from divmorph.pipeline import export_all, train_teachers
from divmorph.pipeline.distill import distill
from divmorph.pipeline.evaluate import evaluate
from divmorph.pipeline.transfer import transfer
from divmorph.pipeline.config import PPO_HYPERPARAMETERS, ConfigError, Profile, load_profile, load_profiles
from divmorph.pipeline.files import atomic_write_json, mark_done, read_done
from divmorph.pipeline.training import TrainingRun, latest_checkpoint, save_checkpoint
from sb3_divmorph.policies import DivMorphPolicy
from divmorph.record import RecordError, find_model, record
from unimal_envs.morphology.loader import MorphologyError, morphology_files

REPO = Path(__file__).resolve().parents[1]
TINY = {"d_model": 16, "n_layers": 1, "ff_dim": 32, "exteroception": {}}


def tiny_profile(folder: Path) -> tuple[Path, Profile]:
    """The shipped demo profile on 1 + 1 robots, 5-step episodes, one teacher (FT), written to a file."""
    values = json.loads(json.dumps(load_profiles()["demo"]))
    values.update(train_robots=1, novel_robots=1, max_episode_steps=5)
    values["teachers"]["tasks"] = ["FT"]
    path = folder / "profiles.yml"
    path.write_text(yaml.safe_dump({"tiny": values}))
    return path, load_profile("tiny", path)


def tiny_model(folder: Path, steps: int = 0) -> PPO:
    """A tiny MetaMorph PPO on FT with VecNormalize, saved as a finished pipeline stage in ``folder``."""
    venv = VecNormalize(
        make_vec_env("Unimal-FT-v0", n_envs=1, env_kwargs=dict(morphologies=morphology_files("train")[:1])),
        norm_obs_keys=["proprioceptive"],
    )
    model = PPO("MetaMorphPolicy", venv, n_steps=32, batch_size=32, n_epochs=1, policy_kwargs=TINY, seed=0)
    if steps:
        model.learn(steps)
    folder.mkdir(parents=True, exist_ok=True)
    model.save(folder / "model.zip")
    venv.save(str(folder / "vecnormalize.pkl"))
    mark_done(folder, num_timesteps=model.num_timesteps)
    return model


# -- environments and robots ----------------------------------------------------------------
def test_a_morphology_prints_on_one_line():
    morphology = unimal_envs.load_morphology(morphology_files("train")[0])
    text = repr(morphology)
    assert "\n" not in text and len(text) < 200
    assert text.startswith("Morphology(name='train-000'") and f"dof={morphology.dof}" in text


def test_a_missing_directory_is_called_one(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for missing in (tmp_path / "nowhere", "runs/robots", "./robots"):
        with pytest.raises(MorphologyError, match="no such directory"):
            morphology_files(missing)
    with pytest.raises(MorphologyError, match="no such directory"):
        gym.make("Unimal-FT-v0", morphologies=str(tmp_path / "nowhere" / "set"))
    # a bare word is still most likely a set name with a typo
    with pytest.raises(MorphologyError, match="unknown morphology set 'trian'"):
        morphology_files("trian")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the display check applies to X11/Wayland")
def test_human_rendering_without_a_display_is_a_python_error_that_suggests_rgb_array(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    for env_id in ("Unimal-FT-v0", "Unimal-MultiTask-v1"):
        with pytest.raises(RuntimeError, match="rgb_array"):
            gym.make(env_id, render_mode="human", morphologies=morphology_files("train")[:1])


def test_the_tour_picture_titles_every_panel(tmp_path, monkeypatch):
    from unimal_envs import demo

    figures = []

    def keep(*args, **kwargs):
        figures.append(real(*args, **kwargs))
        return figures[-1]

    real = demo.robot_figure
    monkeypatch.setattr(demo, "robot_figure", keep)
    demo.main(["--count", "2", "--gaits", "1", "--video-steps", "3", "--out", str(tmp_path), "--no-progress"])
    (figure,) = figures
    titles = [ax.get_title() for ax in figure.axes if ax.images]
    names = [line.split("|")[1].strip() for line in (tmp_path / "summary.md").read_text().splitlines() if line.startswith("| train-")]
    assert len(titles) == len(names) == 2
    for title, name in zip(titles, names):
        assert title.startswith(f"{name}: ") and "limbs" in title and "dof" in title
    assert "train" in figure._suptitle.get_text() and "seed 0" in figure._suptitle.get_text()
    assert (tmp_path / "robots.png").stat().st_size > 10_000


# -- policies -------------------------------------------------------------------------------
def test_the_policies_train_with_a2c_too():
    venv = make_vec_env("Unimal-FT-v0", n_envs=1, env_kwargs=dict(morphologies=morphology_files("train")[:1]))
    gates = dict(n_morph_tailors=4, n_task_tailors=4, top_k_morph=2, top_k_task=2)
    for policy, kwargs in (("MetaMorphPolicy", TINY), ("DivMorphPolicy", {**TINY, **gates})):
        model = A2C(policy, venv, n_steps=4, policy_kwargs=kwargs, seed=0)
        model.learn(8)
        assert model.num_timesteps == 8


def test_a_bad_top_k_names_its_gate():
    env = gym.make("Unimal-FT-v0", morphologies=morphology_files("train")[:1])
    args = (env.observation_space, env.action_space, lambda _: 1e-3)
    with pytest.raises(ValueError, match=r"morphology gate \(top_k_morph.*\[1, 4\].*got 6"):
        DivMorphPolicy(*args, **TINY, n_morph_tailors=4, top_k_morph=6)
    with pytest.raises(ValueError, match=r"task gate \(top_k_task.*got 0"):
        DivMorphPolicy(*args, **TINY, n_task_tailors=4, top_k_task=0)


# -- pipeline messages and files ------------------------------------------------------------
def test_an_override_typo_names_the_profile_file_and_lists_only_ppo_arguments(tmp_path):
    values = load_profiles()["demo"]
    values["teachers"]["overrides"]["n_step"] = 256
    path = tmp_path / "mine.yml"
    path.write_text(yaml.safe_dump({"mine": values}))
    with pytest.raises(ConfigError) as error:
        load_profile("mine", path)
    message = str(error.value)
    assert str(path) in message and "teachers.overrides" in message and "['n_step']" in message
    listed = message.split("PPO hyperparameters: ")[1]
    assert "'n_steps'" in listed and "'n_envs'" in listed
    for not_a_choice in ("_init_setup_model", "env_wrapper", "frame_stack", "'seed'", "'device'", "'verbose'"):
        assert not_a_choice not in listed
    import inspect

    assert set(PPO_HYPERPARAMETERS) <= set(inspect.signature(PPO.__init__).parameters)


def test_names_are_checked_before_anything_is_announced(tmp_path, capsys):
    _, profile = tiny_profile(tmp_path)
    out = tmp_path / "run"
    with pytest.raises(ConfigError, match="unknown task"):
        train_teachers(profile, out, ["FT", "Walk"])
    with pytest.raises(ConfigError, match="no teacher"):
        train_teachers(profile, out, ["FT", "Escape"])
    with pytest.raises(ConfigError, match=r"\['FT'\] not one of"):
        transfer(profile, out, ["Escape", "FT"])
    with pytest.raises(ConfigError, match=r"unknown task\(s\) \['Nope'\]"):
        export_all(profile, out, ["FT", "Nope"])
    assert capsys.readouterr().out == ""  # nothing was announced as if it were going to run


def test_finished_stages_say_they_are_skipped(tmp_path, capsys):
    _, profile = tiny_profile(tmp_path)
    out = tmp_path / "run"
    for folder in ("teachers/FT", "student", "transfer/Escape/divmorph", "transfer/Escape/scratch", "evaluate"):
        mark_done(out / folder)
    train_teachers(profile, out)
    distill(profile, out)
    transfer(profile, out)
    evaluate(profile, out)
    printed = capsys.readouterr().out
    for stage in ("[teachers] FT", "[distill]", "[transfer] Escape (divmorph)", "[transfer] Escape (scratch)", "[evaluate]"):
        assert any(line.startswith(stage) and "skipped" in line for line in printed.splitlines()), (stage, printed)


def test_a_resumed_run_says_from_which_step(tmp_path, capsys):
    folder = tmp_path / "teacher"
    model = tiny_model(tmp_path / "first", steps=32)
    save_checkpoint(model, folder / "checkpoints")
    make_env = lambda: make_vec_env("Unimal-FT-v0", n_envs=1, env_kwargs=dict(morphologies=morphology_files("train")[:1]))  # noqa: E731
    TrainingRun(folder, 64, 1000, make_model=None, make_env=make_env, progress_bar=False).run()
    assert "resuming from step 32 of 64" in capsys.readouterr().out


class _InterruptAt(BaseCallback):
    """Raises KeyboardInterrupt (what SIGINT raises in Python) once ``steps`` steps are done: in the
    middle of collecting a rollout (``where="step"``), or once a whole rollout was collected and is
    being learnt from (``where="rollout_end"``, as DAgger's labelling and update run)."""

    def __init__(self, steps: int, where: str):
        super().__init__()
        self.steps, self.where = steps, where

    def _on_step(self) -> bool:
        if self.where == "step" and self.num_timesteps >= self.steps:
            raise KeyboardInterrupt
        return True

    def _on_rollout_end(self) -> None:
        if self.where == "rollout_end" and self.num_timesteps >= self.steps:
            raise KeyboardInterrupt


@pytest.mark.parametrize(
    "where, interrupted_at, saved_at",
    [
        ("step", 80, 64),  # in the third rollout (steps 64-95): it is collected again
        ("rollout_end", 96, 96),  # the third rollout collected and being learnt from: not collected twice
    ],
)
def test_an_interrupted_run_keeps_its_steps_and_the_same_command_resumes_from_them(tmp_path, capsys, where, interrupted_at, saved_at):
    """A run stopped by SIGINT between checkpoints (a GPU window's time limit) saves where it stopped:
    the next attempt resumes from there with the weights it had, not from the last periodic checkpoint."""
    folder = tmp_path / "teacher"
    make_env = lambda: make_vec_env("Unimal-FT-v0", n_envs=1, env_kwargs=dict(morphologies=morphology_files("train")[:1]))  # noqa: E731
    make_model = lambda: PPO("MetaMorphPolicy", make_env(), n_steps=32, batch_size=32, n_epochs=1, policy_kwargs=TINY, seed=0)  # noqa: E731
    stop = _InterruptAt(interrupted_at, where)
    run = TrainingRun(folder, 256, 10_000, make_model=make_model, make_env=make_env, callbacks=[stop], progress_bar=False)
    with pytest.raises(KeyboardInterrupt):
        run.run()
    assert "[interrupted]" in capsys.readouterr().out
    saved = latest_checkpoint(folder / "checkpoints")
    # the periodic interval (10,000) was never reached
    assert saved is not None and saved.name == f"step-{saved_at:012d}"
    weights = PPO.load(saved / "model.zip").policy.state_dict()
    assert not (folder / "done.json").exists()

    TrainingRun(folder, 256, 10_000, make_model=None, make_env=make_env, progress_bar=False).run()
    assert f"resuming from step {saved_at} of 256" in capsys.readouterr().out
    assert read_done(folder)["num_timesteps"] == 256
    # the interrupted attempt had learnt (two updates): what was saved is not the fresh model's weights
    fresh = make_model().policy.state_dict()
    assert any(not th.equal(weights[key], fresh[key]) for key in fresh)


def test_results_files_are_readable_by_others(tmp_path):
    old = os.umask(0o022)
    try:
        atomic_write_json(tmp_path / "a.json", {"x": 1})
        os.umask(0o027)
        atomic_write_json(tmp_path / "b.json", {"x": 1})
    finally:
        os.umask(old)
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o644  # mkstemp alone gives 0600
    assert (tmp_path / "b.json").stat().st_mode & 0o777 == 0o640  # the umask decides, as for open()


def test_no_progress_silences_the_evaluate_bar(tmp_path, capfd):
    profiles, _ = tiny_profile(tmp_path)
    for flag, out in ((["--no-progress"], tmp_path / "quiet"), ([], tmp_path / "loud")):
        tiny_model(out / "teachers" / "FT")
        assert cli(["evaluate", "--profile", "tiny", "--profiles", str(profiles), "--out", str(out), *flag]) == 0
        err = capfd.readouterr().err
        assert ("[evaluate]" in err) == (not flag), err  # the bar is drawn unless --no-progress


# -- rl-zoo and recording -------------------------------------------------------------------
def test_the_zoo_extra_has_what_rl_zoo_plots_imports():
    extra = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]["zoo"]
    assert {"pandas", "seaborn"} <= {name.split(">")[0].split("=")[0].strip() for name in extra}
    import rl_zoo3.plots.plot_from_file  # noqa: F401  (imports pandas and seaborn)


def test_the_shipped_zoo_entries_for_rl_zoo_and_for_your_own_ppo(tmp_path, monkeypatch):
    import sb3_divmorph.zoo as zoo

    monkeypatch.chdir(tmp_path)  # found without the repository as working directory
    assert zoo.hyperparams == yaml.safe_load((REPO / "zoo_configs" / "ppo.yml").read_text())
    hp = zoo.zoo_hyperparams("Unimal-FT-v0", overrides={"n_envs": 2})
    assert (hp.n_envs, hp.ppo_kwargs["n_steps"], hp.ppo_kwargs["batch_size"], hp.policy_kwargs["preset"]) == (2, 512, 512, "small")
    assert callable(hp.ppo_kwargs["learning_rate"]) and hp.normalize["norm_obs_keys"] == ["proprioceptive"]
    assert load_profile("demo").name == "demo"


def test_record_finds_the_statistics_and_the_task(tmp_path):
    teacher = tmp_path / "run" / "teachers" / "FT"
    tiny_model(teacher)
    saved = find_model(teacher)
    assert (saved.model, saved.normalizer, saved.env_id) == (teacher / "model.zip", teacher / "vecnormalize.pkl", "Unimal-FT-v0")
    arm = tmp_path / "run" / "transfer" / "Escape" / "divmorph"
    arm.mkdir(parents=True)
    (arm / "model.zip").write_bytes(b"")
    assert find_model(arm).env_id == "Unimal-Escape-v0" and find_model(arm).normalizer is None

    # an rl-zoo run folder whose config says it normalised, but whose statistics are gone
    zoo = tmp_path / "logs" / "ppo" / "Unimal-VT-v0_2"
    (zoo / "Unimal-VT-v0").mkdir(parents=True)
    (zoo / "Unimal-VT-v0.zip").write_bytes(b"")
    (zoo / "Unimal-VT-v0" / "config.yml").write_text(
        "!!python/object/apply:collections.OrderedDict\n- - - n_envs\n    - 4\n  - - normalize\n"
        "    - dict(norm_obs=True, norm_reward=True, norm_obs_keys=['proprioceptive'])\n"
    )
    with pytest.raises(RecordError, match="vecnormalize.pkl is missing"):
        find_model(zoo)
    with pytest.raises(RecordError, match="no such file or directory"):
        find_model(tmp_path / "nothing")


def test_record_films_a_pipeline_stage_on_its_own_robots_outside_its_folder(tmp_path, capsys, monkeypatch):
    import argparse
    import inspect
    import json

    import imageio.v3 as iio

    import unimal_envs.rendering as rendering
    from divmorph.record import add_arguments

    student = tmp_path / "run" / "student"
    tiny_model(student)
    # The run records the robots it trained on: train-002 here, not the set's first robot.
    (tmp_path / "run" / "robot_sets.json").write_text(json.dumps({"train": {"set": "train", "robots": ["train-002"]}}))
    streamed = []
    original = rendering.write_video
    monkeypatch.setattr(
        rendering, "write_video", lambda frames, *a, **k: streamed.append(inspect.isgenerator(frames)) or original(frames, *a, **k)
    )
    monkeypatch.chdir(tmp_path)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    with pytest.raises(RecordError, match="pass --task"):  # a multi-task student: which task?
        record(parser.parse_args([str(student)]))
    video = record(parser.parse_args([str(student), "--task", "FT", "--steps", "4", "--width", "48", "--height", "48", "--no-progress"]))
    assert video == Path("videos") / "student-Unimal-FT-v0.mp4" and not (student / "videos").exists()
    assert streamed == [True], "frames go to the encoder as they are rendered, not as a list"
    frames = iio.imread(video)
    assert frames.shape[1:] == (48, 48, 3) and 2 <= len(frames) <= 5 and np.ptp(frames) > 0
    assert "episode 0: train-002" in capsys.readouterr().out


def test_record_best_films_the_training_robot_the_run_evaluated_best(tmp_path, capsys, monkeypatch):
    """``--robot best`` picks the model's best *training* robot from its run's ``evaluate/returns.csv``
    (a better held-out robot, or another model's best, is not chosen); outside an evaluated run it
    says what is missing."""
    import argparse
    import json

    import pandas as pd

    from divmorph.record import add_arguments

    run = tmp_path / "run"
    teacher = run / "teachers" / "FT"
    tiny_model(teacher)
    (run / "run.json").write_text(json.dumps({"configuration": {}}))
    (run / "robot_sets.json").write_text(json.dumps({"train": {"set": "train", "robots": ["train-001", "train-002", "train-003"]}}))
    rows = [
        ("teacher", "FT", "train", "train-001", 10.0),
        ("teacher", "FT", "train", "train-002", 30.0),
        ("teacher", "FT", "train", "train-003", 20.0),
        ("teacher", "FT", "novel", "train-001", 99.0),  # held out: never the showcase's choice
        ("student", "FT", "train", "train-003", 99.0),  # another model's
        ("teacher", "VT", "train", "train-001", 99.0),  # another task's
    ]
    (run / "evaluate").mkdir()
    pd.DataFrame(rows, columns=["model", "task", "split", "morphology", "return"]).assign(episode=0, length=10, seed=None).to_csv(
        run / "evaluate" / "returns.csv", index=False
    )
    monkeypatch.chdir(tmp_path)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    record(parser.parse_args([str(teacher), "--robot", "best", "--steps", "3", "--width", "32", "--height", "32", "--no-progress"]))
    out = capsys.readouterr().out
    assert "train-002 (mean return 30.0)" in out and "episode 0: train-002" in out
    from divmorph.pretrained import load_pretrained

    assert [robot for robot, _ in load_pretrained(teacher).best_robots(n=2)] == ["train-002", "train-003"]
    # with no --robot the film shows the same robot: a newcomer's first film is not of a robot that falls
    gif = tmp_path / "default.gif"
    record(parser.parse_args([str(teacher), "--steps", "12", "--width", "32", "--height", "32", "--no-progress", "--out", str(gif)]))
    captured = capsys.readouterr()
    assert "no --robot: filming train-002" in captured.out and "episode 0: train-002" in captured.out
    # and it says how many frames the file holds (a GIF keeps one in five), not how many were simulated
    import imageio.v2 as imageio

    held = len(imageio.mimread(gif))
    assert held < 12 and f"[record] {held} frames (of " in captured.out
    (run / "evaluate" / "returns.csv").unlink()
    with pytest.raises(RecordError, match="has no evaluation"):
        record(parser.parse_args([str(teacher), "--robot", "best", "--no-progress"]))
    record(parser.parse_args([str(teacher), "--steps", "2", "--width", "32", "--height", "32", "--no-progress"]))
    captured = capsys.readouterr()
    assert "filming the first robot, train-001, which need not be one the model does well on" in captured.err


def test_a_truncated_or_foreign_model_file_is_refused_by_name(tmp_path, capsys):
    """A model cut off by a copy (or another file named model.zip) is refused naming the file, by
    ``load_pretrained`` and by ``divmorph record`` -- before record asks which task (break: drop
    ``check_archive`` -> SB3's raw "wasn't a zip-file", and record first asks for --task)."""
    from divmorph.cli import main as cli
    from divmorph.pretrained import PretrainedError, load_pretrained

    student = tmp_path / "run" / "student"
    tiny_model(student)
    whole = (student / "model.zip").read_bytes()
    for name, content in {"truncated": whole[: len(whole) // 2], "foreign": b"not a model"}.items():
        (student / "model.zip").write_bytes(content)
        with pytest.raises(PretrainedError, match="truncated or not a model archive"):
            load_pretrained(student)
        assert cli(["record", str(student), "--no-progress"]) == 2, name
        err = capsys.readouterr().err
        assert f"{student / 'model.zip'}: truncated or not a model archive" in err and "--task" not in err, name


def test_commands_that_read_a_run_name_a_missing_folder_and_transfer_help_lists_the_arms(tmp_path, capsys):
    from divmorph.cli import main as cli
    from divmorph.pipeline.arms import ARMS

    missing = tmp_path / "no-such-run"
    for command in ("evaluate", "report", "export"):
        assert cli([command, "--run", str(missing)]) == 2
        assert f"no such run folder: {missing}" in capsys.readouterr().err
        assert not missing.exists(), "a typo must not create a run folder"
    with pytest.raises(SystemExit):
        cli(["transfer", "--help"])
    shown = "".join(capsys.readouterr().out.split())  # argparse wraps lines, also at hyphens
    assert all(name in shown for name in ARMS), shown


def test_the_command_overview_lists_every_command_without_importing_torch():
    import subprocess

    from divmorph.cli import build_parser

    # in a fresh interpreter: this test process has imported torch long ago
    code = (
        "import sys\nfrom divmorph.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        "print([name for name in ('torch', 'sb3_divmorph', 'stable_baselines3') if name in sys.modules])"
    )
    shown = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO).stdout
    assert shown.strip().endswith("[]"), "divmorph --help imported the library: " + shown.splitlines()[-1]
    commands = next(action for action in build_parser()._actions if action.dest == "command").choices
    assert set(commands) >= {"pipeline", "transfer", "evaluate", "record", "plot", "branch"}
    assert all(f"    {name}" in shown for name in commands), "the overview lists every command of the full parser"


def test_off_policy_algorithms_say_the_policies_are_on_policy_and_robots_can_be_named():
    import gymnasium as gym
    from stable_baselines3 import SAC

    import sb3_divmorph  # noqa: F401
    import unimal_envs  # noqa: F401
    from unimal_envs.morphology.loader import MorphologyError, morphology_files

    with pytest.raises(TypeError, match="DivMorphPolicy is an on-policy actor-critic policy.*PPO or A2C"):
        SAC("DivMorphPolicy", gym.make("Unimal-FT-v0", morphologies=["train-000"]))
    named = morphology_files(["train-003", "novel-001"])
    assert [p.stem for p in named] == ["train-003", "novel-001"] and all(p.is_file() for p in named)
    with pytest.raises(MorphologyError, match="no robot named 'trian-003'"):
        morphology_files(["trian-003"])


def test_plot_draws_rl_zoo_monitor_files_and_pipeline_logs_headless(tmp_path, capsys):
    import json

    import imageio.v3 as iio

    from divmorph.cli import main as cli

    zoo = tmp_path / "logs" / "ppo" / "Unimal-FT-v0_1"
    zoo.mkdir(parents=True)
    for rank in range(2):  # SB3 Monitor files: a JSON header line, then r,l,t per episode
        rows = "\n".join(f"{10.0 * i + rank},{100},{i + 0.5 * rank}" for i in range(30))
        (zoo / f"{rank}.monitor.csv").write_text("#" + json.dumps({"t_start": 0, "env_id": "Unimal-FT-v0"}) + "\nr,l,t\n" + rows + "\n")
    stage = tmp_path / "run" / "teachers" / "FT" / "logs" / "run-0"
    stage.mkdir(parents=True)
    (stage / "progress.csv").write_text("time/total_timesteps,rollout/ep_rew_mean\n2048,1.5\n4096,3.0\n6144,8.0\n")
    out = tmp_path / "curves.png"
    assert cli(["plot", str(zoo), str(tmp_path / "run" / "teachers" / "FT"), "--out", str(out), "--window", "5"]) == 0
    image = iio.imread(out)
    assert image.ndim == 3 and image.shape[0] > 200 and image.std() > 10
    assert "2 curve(s)" in capsys.readouterr().out
    from divmorph.plot import learning_curve

    steps, returns, source = learning_curve(zoo, window=5)
    assert len(steps) == 60 - 4 and steps[-1] == 6000 and "60 episodes" in source  # every episode, cumulative steps
    assert cli(["plot", str(tmp_path / "empty-run"), "--out", str(tmp_path / "x.png")]) == 2
    assert "no such folder" in capsys.readouterr().err and not (tmp_path / "x.png").exists()
    (tmp_path / "bare").mkdir()
    assert cli(["plot", str(tmp_path / "bare"), "--out", str(tmp_path / "x.png")]) == 2
    assert "holds no SB3 Monitor files" in capsys.readouterr().err


def test_the_report_says_which_robots_are_novel():
    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.report import _robots_sentence

    assert "novel: robots 11-20 of `unimals100-train`" in _robots_sentence(load_profile("cpu"))
    assert "novel: the first 4 of `novel`" in _robots_sentence(load_profile("demo"))


def test_a_failed_redo_puts_the_good_results_back(tmp_path, monkeypatch, capsys):
    """``divmorph evaluate --redo evaluate`` moves the old evaluation aside first; when the new one
    fails (here: a model file that does not load), the old one is back where it was."""
    import zipfile

    from divmorph.cli import main as cli
    import importlib

    # the stage's module (the package's `evaluate` attribute is the stage function)
    evaluate_stage = importlib.import_module("divmorph.pipeline.evaluate")

    run = tmp_path / "run"
    (run / "evaluate").mkdir(parents=True)
    (run / "evaluate" / "returns.csv").write_text("model,task,return\nteacher,FT,1863.0\n")
    common = ["--profile", "demo", "--out", str(run), "--no-progress", "--set", "train_robots=1", "--set", "novel_robots=1"]

    def broken(*args, **kwargs):
        raise zipfile.BadZipFile("File is not a zip file: model.zip")

    monkeypatch.setattr(evaluate_stage, "evaluate", broken)
    with pytest.raises(zipfile.BadZipFile):
        cli(["evaluate", *common, "--redo", "evaluate"])
    assert (run / "evaluate" / "returns.csv").read_text().endswith("1863.0\n"), "the good evaluation is back"
    assert "the previous evaluate folders are back" in capsys.readouterr().err
    monkeypatch.setattr(evaluate_stage, "evaluate", lambda *a, **k: (_ for _ in ()).throw(FileNotFoundError("no model.zip in teachers/FT")))
    assert cli(["evaluate", *common, "--redo", "evaluate"]) == 2
    assert (run / "evaluate" / "returns.csv").is_file()


@pytest.mark.shipped_results
def test_evaluate_a_selection_of_a_shipped_run_into_a_folder_of_ones_own(official_cache, tmp_path, capsys):
    import csv

    from divmorph.cli import main as cli

    run = Path(__file__).resolve().parents[1] / "results" / "cpu100"
    record = (run / "run.json").read_text()
    evaluated = run / "evaluate" / "returns.csv"
    shipped = evaluated.read_text() if evaluated.is_file() else None
    into = tmp_path / "mine"
    assert (
        cli(
            [
                "evaluate",
                "--run",
                str(run),
                "--model",
                "student-distilled",
                "--task",
                "FT",
                "--split",
                "train",
                "--episodes",
                "1",
                "--into",
                str(into),
                "--no-progress",
            ]
        )
        == 0
    )
    rows = list(csv.DictReader(open(into / "returns.csv")))
    assert len(rows) == 100 and {(r["model"], r["task"], r["split"]) for r in rows} == {("student-distilled", "FT", "train")}
    assert (run / "run.json").read_text() == record and (evaluated.read_text() if evaluated.is_file() else None) == shipped
    assert cli(["evaluate", "--run", str(run), "--model", "teachr", "--into", str(into), "--no-progress"]) == 2
    assert "no finished model matches models=['teachr']" in capsys.readouterr().err
    assert cli(["evaluate", "--run", str(run), "--model", "teacher", "--into", str(run / "evaluate"), "--no-progress"]) == 2
    assert "the run's own evaluation" in capsys.readouterr().err


def test_no_ablation_figure_without_an_ablation_and_legends_stay_off_the_curves(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.curves import write_eval
    from divmorph.pipeline.figures import make_figure, outside_legend

    profile = load_profile("demo")
    task = profile.transfer.tasks[0]

    def curve(arm: str) -> None:
        rows = [
            {"timesteps": t, "split": split, "robot": "train-000", "episode": 0, "return": float(t), "length": 10}
            for t in (0, 100, 200)
            for split in ("train", "novel")
        ]
        write_eval(tmp_path / "transfer" / task / arm / "seed-0" / "eval.csv", rows)

    curve("divmorph")
    assert make_figure(profile, tmp_path, "ablation") is None, "DivMorph alone is no ablation figure"
    assert make_figure(profile, tmp_path, "transfer-train") is not None
    curve("no-orthogonality")
    assert make_figure(profile, tmp_path, "ablation") is not None
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1], label="a")
    outside_legend(ax)
    fig.canvas.draw()
    legend, axes = ax.get_legend().get_window_extent(), ax.get_window_extent()
    assert legend.y1 <= axes.y0, "the legend sits below the axes"
    plt.close(fig)


def test_robot_set_records_name_no_machine_paths():
    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.robots import robot_set_record

    record = robot_set_record(load_profile("demo"))
    assert record["train"]["folder"] == "unimal_envs/data/morphologies/train"
    assert not any(entry["folder"].startswith(("/", str(Path.home()))) for entry in record.values())


def test_bad_inputs_name_the_problem(tmp_path, capsys):
    """Each bad input stops with a message that names it (and writes nothing), rather than a
    backend's error from deep inside (issue 46)."""
    import argparse

    from divmorph.cli import main as divmorph_main
    from divmorph.record import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    with pytest.raises(RecordError, match=r"\.mp4 or \.gif"):
        record(parser.parse_args([str(tmp_path / "run" / "student"), "--out", str(tmp_path / "clip")]))
    with pytest.raises(ValueError, match="world_cache_size"):
        gym.make("Unimal-FT-v0", world_cache_size=-1)
    with pytest.raises(ValueError, match="reset_noise_scale"):
        gym.make("Unimal-FT-v0", reset_noise_scale=-1)
    out = tmp_path / "run"
    assert divmorph_main(["teachers", "--profile", "demo", "--out", str(out), "--set", "teachers.n_timesteps=-5000"]) == 2
    message = capsys.readouterr().err
    assert "--set teachers.n_timesteps=-5000" in message and "positive whole number" in message
    assert divmorph_main(["teachers", "--profile", "demo", "--out", str(out), "--task", "Escpe"]) == 2
    assert "unknown task(s) 'Escpe' (did you mean 'Escape'?)" in capsys.readouterr().err
    assert not (out / "teachers").exists()
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "examples/distill_dagger.py", "--steps", "-1", "--out", str(tmp_path / "example")],
        capture_output=True,
        text=True,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert done.returncode == 2 and "--steps must be a positive number" in done.stderr and not (tmp_path / "example").exists()


def same_episode(a: dict, b: dict) -> bool:
    """Two evaluation rows describe the same episode: a batch of 3 and a batch of 1 run the policy's
    matmuls in a different order, so returns agree to float32 rounding, not bit for bit (and a return
    near 0 only to an absolute tolerance: 60 steps carry the rounding into the last digits of 0.117)."""
    rest_a = {k: v for k, v in a.items() if k != "return"}
    rest_b = {k: v for k, v in b.items() if k != "return"}
    return rest_a == rest_b and a["return"] == pytest.approx(b["return"], rel=1e-5, abs=1e-3)


def test_load_pretrained_names_the_robot_that_ran_and_keeps_the_run_settings(tmp_path):
    """``load_pretrained(folder).evaluate`` labels each return with the robot that produced it: a robot's
    row in a batch equals that robot run alone with the same seed, whatever its place in the batch, and
    its episode e is the env's episode reset with ``episode_seed(seed, robot, e)``. The run's env settings come with the
    model, and overriding one warns, naming it."""
    import json
    import warnings

    from divmorph.pipeline.curves import episode_seed
    from divmorph.pretrained import load_pretrained

    run = tmp_path / "run"
    tiny_model(run / "teachers" / "FT", steps=64)
    (run / "robot_sets.json").write_text(json.dumps({"train": {"set": "train", "robots": ["train-003", "train-001", "train-005"]}}))
    (run / "run.json").write_text(json.dumps({"configuration": {"height_reference": "ground"}}))
    model = load_pretrained(run / "teachers" / "FT")
    assert [r.stem for r in model.robots] == ["train-003", "train-001", "train-005"]
    assert model.env_id == "Unimal-FT-v0" and model.env_kwargs == {"height_reference": "ground"}
    together = {row["robot"]: row for row in model.evaluate(max_episode_steps=60, seed=10)}
    assert sorted(together) == ["train-001", "train-003", "train-005"]
    for robot in ["train-003", "train-001", "train-005"]:
        alone = model.evaluate([robot], max_episode_steps=60, seed=10)[0]
        assert same_episode(alone, together[robot]), robot
    two = {row["episode"]: row for row in model.evaluate(["train-001"], episodes=2, max_episode_steps=60, seed=10)}
    assert same_episode(two[0], together["train-001"])
    # episode 1, played by hand from its reset seed, is the evaluation's episode 1
    env = model.make_env("train-001", max_episode_steps=60)
    obs, _ = env.reset(seed=episode_seed(10, "train-001", 1))
    total, done = 0.0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(model.predict(obs))
        total, done = total + reward, terminated or truncated
    assert total == pytest.approx(two[1]["return"], rel=1e-5, abs=1e-3)
    env = model.make_env("train-001", max_episode_steps=5)
    assert env.unwrapped.height_reference == "ground" and [m.name for m in env.unwrapped.morphologies] == ["train-001"]
    obs, _ = env.reset(seed=0)
    assert model.predict(obs).shape == env.action_space.shape
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.make_env("train-001", height_reference="world")
    assert any("height_reference='ground'" in str(w.message) for w in caught)


def test_evaluation_rows_come_in_the_order_asked_not_the_order_episodes_end():
    """Robot 0's episodes last 5 steps, robot 1's 2: robot 1 finishes first and more often, yet the
    rows list robot 0's episodes first, each robot's in order (break: return the rows as they finish)."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

    from divmorph.pipeline.curves import rollout_returns

    class Fixed(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (1,))
        action_space = gym.spaces.Box(-1, 1, (1,))

        def __init__(self, length: int):
            self.length, self.t = length, 0

        def reset(self, *, seed=None, options=None):
            self.t = 0
            return np.zeros(1, np.float32), {}

        def step(self, action):
            self.t += 1
            return np.zeros(1, np.float32), float(self.length), self.t >= self.length, False, {}

    class Still:
        def predict(self, obs, deterministic=True):
            return np.zeros((len(obs), 1), np.float32), None

    venv = VecMonitor(DummyVecEnv([lambda: Fixed(5), lambda: Fixed(2)]))
    rows = rollout_returns(Still(), venv, [Path("slow.xml"), Path("fast.xml")], episodes=2)
    assert [(r["robot"], r["episode"], r["length"]) for r in rows] == [("slow", 0, 5), ("slow", 1, 5), ("fast", 0, 2), ("fast", 1, 2)]


def test_a_run_with_a_goal_range_runs_its_models_with_it(tmp_path):
    """A run recorded with ``goal_range`` gives it to every env its models are run in (beside the
    settings in ``env.json``), and its profile gives it to every env of its stages (break: drop the key
    from ``trained_env_kwargs`` -> the model's PointNav env observes the raw ~30 m goal)."""
    import json

    import numpy as np

    from divmorph.pipeline.config import ConfigError, load_profile
    from divmorph.pipeline.envs import profile_env_kwargs
    from divmorph.pretrained import load_pretrained

    run = tmp_path / "run"
    tiny_model(run / "teachers" / "FT", steps=64)
    (run / "run.json").write_text(json.dumps({"configuration": {"height_reference": "world", "goal_range": 10}}))
    model = load_pretrained(run / "teachers" / "FT")
    assert model.env_kwargs.get("goal_range") == 10.0
    obs, _ = model.make_env("train-001", task="PointNav").reset(seed=3)
    assert np.linalg.norm(obs["goal"]) == pytest.approx(10, rel=1e-5)
    assert profile_env_kwargs(load_profile("demo", overrides={"goal_range": 10})) == {"goal_range": 10.0}
    assert profile_env_kwargs(load_profile("demo")) == {}
    with pytest.raises(ConfigError, match="goal_range must be null or a distance"):
        load_profile("demo", overrides={"goal_range": -1})


def test_an_rl_zoo_run_is_filmed_and_loaded_on_the_robots_of_its_env_kwargs(tmp_path):
    """rl-zoo saves ``--env-kwargs`` in ``<env id>/args.yml``: the model's robots and settings come from there."""
    zoo = tmp_path / "logs" / "ppo" / "Unimal-FT-v0_1"
    (zoo / "Unimal-FT-v0").mkdir(parents=True)
    tiny_model(tmp_path / "stage").save(zoo / "Unimal-FT-v0.zip")
    (tmp_path / "stage" / "vecnormalize.pkl").rename(zoo / "Unimal-FT-v0" / "vecnormalize.pkl")
    (zoo / "Unimal-FT-v0" / "args.yml").write_text(
        "!!python/object/apply:collections.OrderedDict\n- - - algo\n    - ppo\n  - - env_kwargs\n"
        "    - morphologies: [train-004]\n      height_reference: ground\n"
    )
    saved = find_model(zoo)
    assert saved.env_kwargs == {"morphologies": ["train-004"], "height_reference": "ground"} and saved.algo == "ppo"
    from divmorph.pretrained import load_pretrained

    model = load_pretrained(zoo)
    assert [r.stem for r in model.robots] == ["train-004"] and model.normalizer is not None


def test_the_version_and_gymnasiums_check_env_without_a_display(monkeypatch, capsys):
    from gymnasium.utils.env_checker import check_env

    from divmorph.cli import main as divmorph_main

    with pytest.raises(SystemExit) as done:
        divmorph_main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.startswith("divmorph ")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    env = gym.make("Unimal-FT-v0", morphologies=morphology_files("train")[:1])
    assert env.metadata["render_modes"] == ["rgb_array"]  # what this machine can serve
    check_env(env.unwrapped)  # makes the env once per listed render mode


def test_one_seed_is_one_episode_in_record_and_evaluate(tmp_path, capsys, monkeypatch):
    """``divmorph record --seed S`` films the episode that ``load_pretrained(...).evaluate(seed=S)``
    (and the examples built on it) reports: the same steps and return for the same robot and seed."""
    import argparse
    import re

    from divmorph.pretrained import load_pretrained
    from divmorph.record import add_arguments

    teacher = tmp_path / "run" / "teachers" / "FT"
    tiny_model(teacher, steps=64)
    monkeypatch.chdir(tmp_path)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for seed in (3, 4):
        record(
            parser.parse_args(
                [
                    str(teacher),
                    "--robot",
                    "train-002",
                    "--seed",
                    str(seed),
                    "--steps",
                    "30",
                    "--width",
                    "32",
                    "--height",
                    "32",
                    "--no-progress",
                ]
            )
        )
        filmed = re.search(r"episode 0: train-002, (\d+) steps, return (-?[\d.]+)", capsys.readouterr().out)
        row = load_pretrained(teacher).evaluate(["train-002"], seed=seed, max_episode_steps=30)[0]
        assert filmed is not None and (int(filmed.group(1)), float(filmed.group(2))) == (
            row["length"],
            pytest.approx(row["return"], abs=0.05),
        )


def test_the_library_loads_a_model_file_with_the_statistics_beside_it(tmp_path):
    """``sb3_divmorph.load_model``: a model file alone (no run folder) acts through the statistics it
    trained with -- found beside it -- and a cut-off file is refused by name (break: drop the
    normaliser lookup -> the actions differ from the normalised ones)."""
    from sb3_divmorph import load_model
    from sb3_divmorph.saved_model import SavedModelError

    model = tiny_model(tmp_path / "stage", steps=64)
    loaded = load_model(tmp_path / "stage" / "model.zip")
    assert loaded.normalizer is not None and not loaded.normalizer.training
    env = gym.make("Unimal-FT-v0", morphologies=morphology_files("train")[:1])
    obs, _ = env.reset(seed=0)
    batch = {key: value[None] for key, value in obs.items()}
    expected, _ = model.predict(loaded.normalizer.normalize_obs(batch), deterministic=True)
    raw, _ = model.predict(batch, deterministic=True)
    assert np.allclose(loaded.predict(batch), expected) and not np.allclose(expected, raw), "the statistics are applied"
    cut = tmp_path / "cut.zip"
    cut.write_bytes((tmp_path / "stage" / "model.zip").read_bytes()[:1000])
    with pytest.raises(SavedModelError, match="truncated or not a model archive"):
        load_model(cut)


def test_divmorph_evaluate_takes_any_model_folder(tmp_path, capsys):
    """``divmorph evaluate FOLDER`` evaluates one saved model (a pipeline stage here; an rl-zoo run
    folder loads the same way) on the robots asked for, naming each, into ``--into``."""
    import csv

    from divmorph.cli import main as divmorph_main

    teacher = tmp_path / "stage" / "teachers" / "FT"
    tiny_model(teacher)
    into = tmp_path / "eval"
    assert divmorph_main(["evaluate", str(teacher), "--robots", "train-001", "--episodes", "2", "--into", str(into)]) == 0
    printed = capsys.readouterr().out
    assert "FT train-001 episode 1: return" in printed and "FT: mean return" in printed
    rows = list(csv.DictReader(open(into / "returns.csv")))
    assert [(r["task"], r["robot"], r["episode"]) for r in rows] == [("FT", "train-001", "0"), ("FT", "train-001", "1")]
    assert divmorph_main(["evaluate", str(tmp_path / "nothing")]) == 2
    assert "no such file or directory" in capsys.readouterr().err


def test_export_finds_a_robot_by_name_among_the_runs_own_robots(official_train):
    """``divmorph export --morphology NAME`` takes any robot of the run's sets (an official robot of a
    ``cpu100``-like run), not only the shipped generated ones; an unknown name says where it looked."""
    from divmorph.cli.export import robot_path as _robot_path
    from divmorph.pipeline.config import load_profile

    profile = load_profile("demo", overrides={"train_set": str(official_train / "xml"), "train_robots": None})
    name = sorted((official_train / "xml").glob("*.xml"))[-1].stem
    assert _robot_path(name, profile).stem == name
    with pytest.raises(ValueError, match="the run's robots"):
        _robot_path("no-such-robot", profile)
    with pytest.raises(ValueError, match="unknown morphology"):
        _robot_path(name)  # without the run: the shipped sets only


def test_command_line_mistakes_are_said_before_torch_loads(tmp_path):
    """An unknown ``--set`` key or task name is refused before the stages (and torch) are imported: the
    command runs with torch made unimportable and still gives the message (break: move the check after
    ``import torch`` in ``run_on_folder`` -> "torch is not to be imported")."""
    import os
    import subprocess
    import sys

    (tmp_path / "sitecustomize.py").write_text(
        "import sys\n"
        "class _NoTorch:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('torch', 'stable_baselines3'):\n"
        "            raise ImportError('torch is not to be imported before the arguments are checked')\n"
        "sys.meta_path.insert(0, _NoTorch())\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(Path(__file__).resolve().parents[1])])}
    cases = {
        ("--set", "teachers.n_timestep=5000"): "section 'teachers': unknown key(s) ['n_timestep']; valid keys:",
        ("--set", "nonsense=1"): "unknown key(s) ['nonsense']",
        ("--set", "teachers"): "--set takes KEY=VALUE",
        ("--task", "Escpe"): "unknown task(s) 'Escpe' (did you mean 'Escape'?)",
    }
    for args, said in cases.items():
        done = subprocess.run(
            [sys.executable, "-m", "divmorph.cli", "teachers", "--profile", "demo", "--out", str(tmp_path / "run"), *args],
            capture_output=True,
            text=True,
            env=env,
            cwd=tmp_path,
            timeout=120,
        )
        assert done.returncode == 2 and said in done.stderr, (args, done.stderr[-2000:])
    assert not (tmp_path / "run").exists()
