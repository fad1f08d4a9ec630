"""Stage 4 — deployment: prune and merge the student into a compact actor per robot and task.

For each robot and task the student's gates are evaluated once, unselected tailors are pruned and
the rest merged (:class:`~sb3_divmorph.deploy.compact.CompactActor`), the observation normalisation is
baked in, and the actor is written as ONNX (``actor.onnx``: ``onnxruntime`` + ``numpy`` run it, see
:mod:`sb3_divmorph.deploy.onnx_actor`) and/or TorchScript (``actor.pt``: ``torch.jit.load`` is all it
needs). The stage checks every written file against the unpruned student on observations of a
short rollout (max |diff| <= 1e-5, or it refuses to write) and reports its size like for like: the
MetaMorph actor of the same task and sizes goes through the same folding, so the reduction counts
pruning only (folding is reported on its own); and its batch-1 CPU latency against the full student.

For a novel task the transferred student (``transfer/<task>/divmorph``) is exported when it
exists, else the distilled student itself (zero-shot). The students distilled with a deployment
diversion (``students/deploy-*``, see :data:`~divmorph.pipeline.students.STUDENTS`) are exported
beside the default one, into ``export/<student>/<robot>-<task>``.

Each report also holds the return of one deterministic episode of the compact actor and of the
unpruned student on the same robot, task and seed (``compact_return``, ``student_return``): the
deployed actor does what its student does, measured rather than assumed.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecNormalize

from sb3_divmorph.algos.distillation import load_normalizer
from sb3_divmorph.deploy.compact import (
    CompactActor,
    actor_inputs,
    actor_parameter_count,
    batch1_latency,
    export_onnx,
    export_torchscript,
    size_comparison,
)
from divmorph.pipeline.config import ConfigError, Profile
from divmorph.pipeline.folders import export_reports, student_folder, transfer_folder  # noqa: F401 -- export_reports re-exported
from divmorph.pipeline.envs import profile_env_kwargs, task_env_name
from divmorph.pipeline.files import DONE, MODEL, atomic_write_json, atomic_write_text, is_done, mark_done, read_done
from divmorph.pipeline.robots import profile_robots
from divmorph.pipeline.training import stage_model, stage_normalizer
from divmorph.pipeline.students import STUDENTS
from sb3_divmorph.policies.morphology_transformer import DivMorphPolicy
from unimal_envs.contract import NOVEL_TASKS, TASK_NAMES
from unimal_envs.tasks import TASKS

#: Largest accepted difference between the exported actor and the student, relative to the size of
#: the student's action means (at least 1): float32 rounding grows with the values (a trained student
#: whose means reach a few units differs by ~1e-5 through another order of operations).
TOLERANCE = 1e-5
#: Deployment file formats: ``onnx`` (onnxruntime + numpy) and ``torchscript`` (torch alone).
FORMATS = ("onnx", "torchscript")


def export_folder(out: Path, robot: str, task: str, student: str = "divmorph") -> Path:
    """``export/<robot>-<task>`` for the DivMorph student, ``export/<student>/<robot>-<task>`` for another."""
    folder = Path(out) / "export"
    return folder / f"{robot}-{task}" if student == "divmorph" else folder / student / f"{robot}-{task}"


def deployment_students(out: Path) -> list[str]:
    """The students the export stage deploys: the DivMorph student and every finished ``deploy-*`` one."""
    return ["divmorph", *(name for name in STUDENTS if name.startswith("deploy-") and is_done(student_folder(out, name)))]


def source_model(out: Path, task: str, student: str = "divmorph") -> tuple[Path, str]:
    """The model to export for ``task``: the transferred student for a novel task if there is one."""
    if student == "divmorph" and task in NOVEL_TASKS and is_done(transfer_folder(out, task, "divmorph")):
        return transfer_folder(out, task, "divmorph"), "transferred student"
    folder = student_folder(out, student)
    if not is_done(folder):
        raise FileNotFoundError(
            f"no distilled student {student!r} in {folder}; run `divmorph distill --out {out} --students {student}` first"
        )
    label = "distilled student" if student == "divmorph" else f"distilled {student} student"
    return folder, label + (" (zero-shot)" if task in NOVEL_TASKS else "")


def current_export(folder: Path, source: Path) -> dict[str, Any] | None:
    """The finished export in ``folder`` if it was made from ``source`` as it is now (same model folder,
    same finishing time), else ``None``."""
    if not is_done(folder):
        return None
    report = json.loads((folder / "report.json").read_text())
    same = report.get("source") == str(source / MODEL) and report.get("source_finished") == read_done(source).get("finished")
    return report if same else None


def episode_return(env: gym.Env, act, seed: int) -> tuple[float, int]:
    """Return and length of one episode of ``act(obs) -> action`` from ``env.reset(seed=seed)``."""
    obs, _ = env.reset(seed=seed)
    total, steps, done = 0.0, 0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(np.clip(act(obs), -1, 1).astype(np.float32))
        total, steps, done = total + float(reward), steps + 1, terminated or truncated
    return total, steps


def _rollout_observations(env: gym.Env, actor: CompactActor, first: dict[str, np.ndarray], steps: int, seed: int) -> dict[str, np.ndarray]:
    observations, obs = [first], first
    rng = np.random.default_rng(seed)
    with th.no_grad():
        for _ in range(steps - 1):
            action = actor(*actor_inputs(obs))[0].numpy()
            action = np.clip(action + rng.normal(0, 0.3, action.shape), -1, 1).astype(np.float32)
            obs, _, terminated, truncated, _ = env.step(action)
            observations.append(obs)
            if terminated or truncated:
                break
    return {k: np.stack([o[k] for o in observations]) for k in first}


def _onnx_runner(path: Path):
    from sb3_divmorph.deploy.onnx_actor import OnnxActor

    actor = OnnxActor(path)
    return lambda observations: th.as_tensor(actor(observations))


def export_actor(
    profile: Profile,
    out: Path,
    robot_file: Path,
    task: str,
    steps: int = 64,
    formats: tuple[str, ...] = FORMATS,
    student: str = "divmorph",
) -> dict[str, Any]:
    """Export one robot x task actor of ``student`` in ``formats``; returns (and writes) its report."""
    if task not in TASK_NAMES:
        raise ConfigError(f"unknown task {task!r}; choose from {list(TASK_NAMES)}")
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise ConfigError(f"unknown export format(s) {bad or list(formats)}; choose from {list(FORMATS)} or 'all'")
    robot_file = Path(robot_file)
    folder = export_folder(out, robot_file.stem, task, student)
    source, source_label = source_model(out, task, student)
    previous = current_export(folder, source)
    print(f"[export] {student}: {robot_file.stem} x {task}" + (f": skipped, already exported in {folder}" if previous else ""))
    if previous is not None:
        return previous
    if is_done(folder):
        # e.g. a zero-shot export of a novel task made before its transfer finished: not reused as if it were the transferred one
        print(f"[export] {folder}: exported from another model than {source / MODEL} ({source_label}); exporting again")
        (folder / DONE).unlink()
    model = PPO.load(stage_model(source), device="cpu")
    policy = model.policy.eval()
    if not isinstance(policy, DivMorphPolicy):
        raise TypeError(f"{source / MODEL} holds a {type(policy).__name__}, not a DivMorph student")
    statistics = stage_normalizer(source)
    normalizer: VecNormalize | None = None if statistics is None else load_normalizer(statistics)

    env = gym.make(
        task_env_name(task), morphologies=[robot_file], max_episode_steps=profile.max_episode_steps, **profile_env_kwargs(profile)
    )
    try:
        first, _ = env.reset(seed=profile.seed)
        actor = CompactActor.from_policy(policy, first, TASKS[task].observation_keys, normalizer)
        observations = _rollout_observations(env, actor, first, steps, profile.seed)

        def compact_act(obs):
            with th.no_grad():
                return actor(*actor_inputs(obs))[0].numpy()

        def student_act(obs):
            batch = {k: v[None] for k, v in obs.items()}
            return policy.predict(batch if normalizer is None else normalizer.normalize_obs(batch), deterministic=True)[0][0]

        compact_return, compact_length = episode_return(env, compact_act, profile.seed)
        student_return, student_length = episode_return(env, student_act, profile.seed)
    finally:
        env.close()

    folder.mkdir(parents=True, exist_ok=True)
    counts = actor.stored_numbers()
    student_actor = actor_parameter_count(policy)
    sizes = size_comparison(policy, actor, first, TASKS[task].observation_keys, normalizer)
    in_train = robot_file.resolve() in {f.resolve() for f in profile_robots(profile, "train")}
    metadata = {
        "robot": robot_file.stem,
        # the robot's set, so that a reader finds its MJCF: morphology_files(robot_set) has robot
        "robot_set": profile.train_set if in_train else profile.novel_set,
        "task": task,
        "student": student,
        "source": str(source / MODEL),
        "source_finished": read_done(source).get("finished"),
        "output": "action means (B,24), 0 on padded slots; clip to [-1, 1] before env.step",
    }
    normalized = observations if normalizer is None else normalizer.normalize_obs(observations)
    with th.no_grad():
        obs_t, _ = policy.obs_to_tensor(normalized)
        distribution = policy.get_distribution(obs_t).distribution
        assert isinstance(distribution, th.distributions.Normal)  # the masked diagonal Gaussian's
        reference = distribution.mean
    one_raw = {k: v[:1] for k, v in observations.items()}
    repeats = profile.export.latency_repeats
    files: dict[str, Any] = {}
    writers = {
        "torchscript": ("actor.pt", export_torchscript, lambda p: lambda obs, m=th.jit.load(str(p)): m(*actor_inputs(obs, batch=True))),
        "onnx": ("actor.onnx", export_onnx, _onnx_runner),
    }
    allowed = TOLERANCE * max(1.0, float(reference.abs().max()))
    for fmt in formats:
        name, write, runner = writers[fmt]
        path = write(actor, first, folder / name, metadata)
        # Check the written file, loaded by its own runtime, against the unpruned student.
        run = runner(path)
        with th.no_grad():
            max_diff = float((reference - run(observations)).abs().max())
        if not max_diff <= allowed:
            path.unlink()
            raise RuntimeError(
                f"exported {fmt} actor differs from the student by {max_diff:.2e} > {allowed:.2e} "
                f"({TOLERANCE} x max(1, largest |action mean| {float(reference.abs().max()):.2f})) ({robot_file.stem}, {task})"
            )
        files[fmt] = {
            "file": name,
            "bytes": path.stat().st_size,
            "max_abs_diff": max_diff,
            "latency_ms": batch1_latency(run, (one_raw,), repeats) * 1e3,
        }

    one_obs, _ = policy.obs_to_tensor(one_raw if normalizer is None else normalizer.normalize_obs(one_raw))

    def student_step(obs):
        return policy.get_distribution(obs).distribution.mean

    student_s = batch1_latency(student_step, (one_obs,), repeats)
    compact_ms = min(f["latency_ms"] for f in files.values())
    report = {
        **metadata,
        "source_label": source_label,
        "real_tokens": int(len(actor.real_tokens)),
        "compact_weights": counts["weights"],
        "compact_normalization_numbers": counts["normalization"],
        "student_actor_parameters": student_actor,
        "metamorph_actor_parameters": sizes["metamorph_actor"],
        "metamorph_folded_weights": sizes["metamorph_folded"],
        "folding_metamorph": sizes["folding"],
        "reduction_vs_metamorph": sizes["reduction"],
        "reduction_vs_student": student_actor / counts["weights"],
        "max_abs_diff": max(f["max_abs_diff"] for f in files.values()),
        "tolerance": allowed,
        "largest_action_mean": float(reference.abs().max()),
        "checked_observations": int(len(observations["proprioceptive"])),
        "formats": files,
        "latency_compact_ms": compact_ms,
        "latency_student_ms": student_s * 1e3,
        "speedup_vs_student": student_s * 1e3 / compact_ms,
        "torch_threads": th.get_num_threads(),
        "compact_return": compact_return,
        "compact_episode_length": compact_length,
        "student_return": student_return,
        "student_episode_length": student_length,
    }
    atomic_write_json(folder / "report.json", report)
    mark_done(folder)
    return report


def export_all(
    profile: Profile,
    out: Path,
    tasks: list[str] | None = None,
    robots: list[Path] | None = None,
    formats: tuple[str, ...] = FORMATS,
    students: list[str] | None = None,
) -> list[dict[str, Any]]:
    """Export every (robot, task) pair of the profile (or the given ones) in ``formats`` and write
    ``export/summary.csv``.

    :param students: the students to deploy (default: :func:`deployment_students`).
    """
    if robots is None:
        n = profile.export.robots_per_split
        robots = profile_robots(profile, "train")[:n] + profile_robots(profile, "novel")[:n]
    tasks = tasks or profile.export.tasks
    # every name is checked before the first one is announced and exported
    unknown = [task for task in tasks if task not in TASK_NAMES]
    if unknown:
        raise ConfigError(f"unknown task(s) {unknown}; choose from {list(TASK_NAMES)}")
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise ConfigError(f"unknown export format(s) {bad or list(formats)}; choose from {list(FORMATS)} or 'all'")
    students = students or deployment_students(out)
    unknown = [name for name in students if name not in STUDENTS or STUDENTS[name].policy is not DivMorphPolicy]
    if unknown:
        raise ConfigError(
            f"cannot deploy {unknown}: not DivMorph students; choose from "
            f"{[n for n, spec in STUDENTS.items() if spec.policy is DivMorphPolicy]}"
        )
    reports = []
    for student in students:
        for task in tasks:
            for robot in robots:
                reports.append(export_actor(profile, out, robot, task, formats=formats, student=student))
    # the summary covers every actor exported into this run folder so far, not only this call's
    everything = [json.loads(p.read_text()) for p in export_reports(out)]
    if everything:
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=list(dict.fromkeys(k for r in everything for k in r)), extrasaction="ignore")
        writer.writeheader()
        writer.writerows(everything)
        atomic_write_text(Path(out) / "export" / "summary.csv", buffer.getvalue())
    return reports
