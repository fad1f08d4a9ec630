"""Stage 5 — evaluation: per-morphology returns on train, novel (and out-of-distribution) robots, and gate activations.

Every model of the run is rolled out deterministically, one env per robot, for ``episodes``
episodes of at most ``max_episode_steps``: teachers on their task, next to the same policy before
training (``teacher-untrained``: the teacher run's initial weights and normaliser, same seed), the
student on every training task and (zero-shot) on the transfer tasks, the other distilled students
(``student-<name>``, e.g. the dense MetaMorph⚗ student and the deployment diversions) on the
training tasks, transferred and from-scratch policies on their novel task (every seed's run), and
the HyperDistill student (when the baseline ran) on the training tasks. A transfer run with
evaluation curves is evaluated on their robots and episodes (``transfer.eval_robots`` /
``eval_episodes``): its last curve evaluation (``eval.csv``, the same deterministic episodes with the
same seed) is reused rather than rolled out again. Rows go to ``evaluate/returns.csv``. The student's gates for all ten task instructions and for
every evaluated robot go to ``evaluate/gates.npz`` (for the correlation heatmaps of the report).
"""

from __future__ import annotations

import csv
import io
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3 import PPO
from tqdm import tqdm

from sb3_divmorph.algos.distillation import load_normalizer
from divmorph.pipeline.arms import ARMS
from divmorph.pipeline.config import Profile
from divmorph.pipeline.curves import EVAL_FILE, evaluate_model, read_eval, robot_venv, rollout_returns  # noqa: F401 -- evaluate_model re-exported
from divmorph.pipeline.folders import TEACHER_RUN, student_folder, teacher_folder, transfer_folder, transfer_seeds, transfer_tasks
from divmorph.pipeline.grid import job_builder
from divmorph.pipeline.envs import profile_env_kwargs, robot_observations, task_env_name
from divmorph.pipeline.files import atomic_save, atomic_write_text, is_done, log_file, mark_done, read_csv_rows
from divmorph.pipeline.robots import profile_robots, profile_splits, trained_instruction, transfer_eval_robots
from divmorph.pipeline.training import has_model, stage_model, stage_normalizer
from divmorph.pipeline.students import STUDENTS
from unimal_envs.contract import TASK_NAMES
from unimal_envs.instructions import shipped_embeddings

COLUMNS = ["model", "task", "split", "morphology", "episode", "return", "length", "seed"]  # seed: a transfer run's
PARTS = "parts"  # evaluate/parts/: the shares of an evaluation that several processes run (--part k/n)


def evaluate_untrained_teacher(
    profile: Profile, out: Path, task: str, robots: list[Path], episodes: int, seed: int
) -> list[dict[str, Any]]:
    """Deterministic returns of ``task``'s teacher *before training*: the model its run starts from
    (same seed, hence the same initial weights, and its fresh observation normaliser)."""
    model = job_builder(TEACHER_RUN)(profile, out, task, progress_bar=False).make_model()
    normalizer = model.get_vec_normalize_env()
    venv = robot_venv(task_env_name(task), robots, profile.max_episode_steps, seed, **profile_env_kwargs(profile))
    rows = rollout_returns(model, venv, robots, episodes, normalizer.normalize_obs if normalizer is not None else None)
    venv.close()
    model.get_env().close()
    return [{"morphology": row.pop("robot"), **row} for row in rows]


def final_evaluation(folder: Path, split: str, robots: list[Path], episodes: int) -> list[dict[str, Any]] | None:
    """A transfer run's last ``eval.csv`` evaluation on ``split`` when it covers exactly ``robots`` x
    ``episodes`` (the evaluation stage's own rollout would repeat it), else ``None``."""
    rows = read_eval(Path(folder) / EVAL_FILE)
    if not rows:
        return None
    last = max(row["timesteps"] for row in rows)
    rows = [row for row in rows if row["timesteps"] == last and row["split"] == split]
    if sorted((row["robot"], row["episode"]) for row in rows) != sorted((r.stem, e) for r in robots for e in range(episodes)):
        return None
    return [{"morphology": row["robot"], "episode": row["episode"], "return": row["return"], "length": row["length"]} for row in rows]


def _can_evaluate(label: str, folder: Path, split: str) -> bool:
    """Whether a job can run: a transfer run whose model is not in this checkout (a recorded run
    ships only its curves) is evaluated only on the splits its curves cover."""
    if not label.startswith("transfer-") or has_model(folder):
        return True
    return any(row["split"] == split for row in read_eval(Path(folder) / EVAL_FILE))


def transfer_robots_and_episodes(
    profile: Profile, split: str, robots: list[Path], episodes: int, episodes_given: bool = False
) -> tuple[list[Path], int]:
    """The robots and episodes a transfer run is evaluated on: those of its evaluation curves (the
    first ``transfer.eval_robots`` of the split, ``transfer.eval_episodes`` each), whose last
    evaluation is then reused; ``robots`` x ``episodes`` when the runs have no curves or when the
    episodes were asked for explicitly."""
    cfg = profile.transfer
    if cfg.eval_every <= 0 or episodes_given:
        return robots, episodes
    return transfer_eval_robots(profile, split), cfg.eval_episodes


def run_instruction(profile: Profile, folder: Path, task: str) -> str | None:
    """The instruction a transfer run trained with: the one its ``source.json`` records
    (``transfer.task_gates: closest``), else the profile's ``transfer.instructions`` (``None``: built-in)."""
    return trained_instruction(folder, None) or profile.transfer.instructions.get(task)


def evaluation_plan(profile: Profile, out: Path) -> list[tuple[str, Path, str]]:
    """``(model label, folder, task)`` of everything there is to evaluate (``teacher-untrained``:
    the teacher's folder, evaluated with its run's initial model)."""
    out = Path(out)
    plan = []

    def trained(folder: Path) -> bool:
        # a finished stage whose model a recorded run does not ship is skipped, and said so
        if is_done(folder) and not has_model(folder):
            print(f"[evaluate] skipping {folder}: its model is not in this checkout (see stage_model)")
        return has_model(folder)

    for t in profile.teachers.tasks:
        if trained(teacher_folder(out, t)):
            plan += [("teacher", teacher_folder(out, t), t), ("teacher-untrained", teacher_folder(out, t), t)]
    if trained(student_folder(out)):
        plan += [("student", student_folder(out), t) for t in (*profile.teachers.tasks, *transfer_tasks(profile, out))]
    for name in STUDENTS:
        if name != "divmorph" and trained(student_folder(out, name)):
            plan += [(f"student-{name}", student_folder(out, name), t) for t in profile.teachers.tasks]
    hyperdistill_student = out / "hyperdistill" / "student"
    if trained(hyperdistill_student):
        plan += [("hyperdistill", hyperdistill_student, t) for t in profile.teachers.tasks]
    for task in transfer_tasks(profile, out):
        for arm in ARMS:
            for seed in transfer_seeds(profile, out, task, arm):
                if is_done(transfer_folder(out, task, arm, seed)):
                    plan.append((f"transfer-{arm}", transfer_folder(out, task, arm, seed), task))
    return plan


def student_gates(out: Path, robots: list[Path], seed: int, **env_kwargs: Any) -> dict[str, np.ndarray]:
    """The student's task gates for every task instruction and morphology gates for ``robots``."""
    model = PPO.load(stage_model(student_folder(out)), device="cpu")
    statistics = stage_normalizer(student_folder(out))
    normalizer = None if statistics is None else load_normalizer(statistics)
    obs = robot_observations(task_env_name("FT"), robots, seed, **env_kwargs)
    if normalizer is not None:
        obs = normalizer.normalize_obs(obs)
    morphology = model.policy.get_gates(obs).morphology.cpu().numpy()
    embeddings = shipped_embeddings()
    one = {k: np.repeat(v[:1], len(TASK_NAMES), axis=0) for k, v in obs.items()}
    one["task_embedding"] = np.stack([embeddings[t] for t in TASK_NAMES]).astype(np.float32)
    task = model.policy.get_gates(one).task.cpu().numpy()
    return {"task_gates": task, "tasks": np.array(TASK_NAMES), "morphology_gates": morphology, "robots": np.array([r.stem for r in robots])}


def evaluate(
    profile: Profile,
    out: Path,
    progress_bar: bool = True,
    models: list[str] | None = None,
    tasks: list[str] | None = None,
    splits: list[str] | None = None,
    episodes: int | None = None,
    into: Path | None = None,
    part: tuple[int, int] | None = None,
) -> Path:
    """Evaluate every finished model of the run; writes ``evaluate/returns.csv`` and ``gates.npz``.

    With a selection, only what is selected is evaluated, into a folder of its own (never the run's
    ``evaluate/``, so a recorded run's results stay as they are):

    :param progress_bar: show a bar over the (model, task, split) jobs.
    :param models: model labels to evaluate (``teacher``, ``teacher-untrained``, ``student``,
        ``student-<name>``, ``hyperdistill``, ``transfer-<arm>``); default all.
    :param tasks: tasks to evaluate on; default all.
    :param splits: ``train``, ``novel`` and/or ``ood`` robots; default every split of the profile.
    :param episodes: episodes per robot (default: the profile's ``evaluate.episodes``).
    :param into: the folder for ``returns.csv`` of a selection (default ``evaluations/<run>-<time>/``
        in the working folder).
    :param part: ``(k, n)``: evaluate only every n-th of the jobs still to do, starting at the k-th
        (1-based), into ``evaluate/parts/`` -- n processes share the run's evaluation, one per core;
        the plain evaluation afterwards merges the parts, evaluates whatever is left, and finishes.
    :raises ValueError: a selection that matches nothing (the message lists what there is); a part
        of a selection, or a part outside 1..n.

    The run's own evaluation is resumable: ``returns.csv`` (and a part's file) is rewritten after
    every (model, task, split), and a rerun keeps every complete one already there.
    """
    out = Path(out)
    selected = any(x is not None for x in (models, tasks, splits, episodes, into))
    folder = out / "evaluate"
    if part is not None and (selected or not 1 <= part[0] <= part[1]):
        raise ValueError(f"a part k/n of the run's evaluation needs 1 <= k <= n and no selection, got {part[0]}/{part[1]}")
    if selected:
        folder = Path(into) if into is not None else Path("evaluations") / f"{out.resolve().name}-{time.strftime('%Y%m%d-%H%M%S')}"
        if folder.resolve() == (out / "evaluate").resolve():
            raise ValueError(f"{folder} is the run's own evaluation; choose another --into for a selection")
    elif is_done(folder) and log_file(folder / "returns.csv") is None:
        print(f"[evaluate] skipped, already evaluated in {folder}")
        return folder
    run_splits = profile_splits(profile)
    unknown_splits = sorted(set(splits or ()) - set(run_splits))
    if unknown_splits:
        raise ValueError(f"unknown robot split(s) {unknown_splits} for profile {profile.name!r}; choose from {list(run_splits)}")
    if episodes is not None and episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    splits_robots = {split: profile_robots(profile, split) for split in (splits or run_splits)}
    plan = evaluation_plan(profile, out)
    if not plan:
        raise FileNotFoundError(f"nothing to evaluate in {out}: run the teachers/distill/transfer stages first")
    if models is not None or tasks is not None:
        chosen = [job for job in plan if (models is None or job[0] in models) and (tasks is None or job[2] in tasks)]
        if not chosen:
            raise ValueError(
                f"no finished model matches models={models}, tasks={tasks} in {out}; there are "
                f"models {sorted({j[0] for j in plan})} on tasks {sorted({j[2] for j in plan})}"
            )
        plan = chosen
    selected_episodes = episodes is not None
    episodes = profile.evaluate.episodes if episodes is None else episodes

    def robots_and_count(label: str, split: str) -> tuple[list[Path], int]:
        if label.startswith("transfer-"):
            return transfer_robots_and_episodes(profile, split, splits_robots[split], episodes, episodes_given=selected_episodes)
        return splits_robots[split], episodes

    jobs = [(label, model, task, split) for label, model, task in plan for split in splits_robots if _can_evaluate(label, model, split)]
    rows: list[dict] = []
    target = folder / "returns.csv"
    if not selected:
        # What is already evaluated -- a finished evaluation (which grows with the models finished
        # after it, e.g. a student distilled later), an interrupted one, or the parts of a shared
        # one -- is kept when it is complete: every robot and episode of that job.
        sources = [target, *sorted((folder / PARTS).glob("*.csv"))]
        rows = complete_rows(sources, {job_key(*job): robots_and_count(job[0], job[3]) for job in jobs})
        evaluated = {row_key(row) for row in rows}
        todo = [job for job in jobs if job_key(*job) not in evaluated]
        if part is not None:
            # a share fixed by the job's place in the plan, not by what is done, so that parts
            # started (or restarted) at different times on the same finished models share no job
            target = folder / PARTS / f"part-{part[0]}-of-{part[1]}.csv"
            share = {job_key(*job) for job in jobs[part[0] - 1 :: part[1]]}
            todo = [job for job in todo if job_key(*job) in share]
            rows = [row for row in rows if row_key(row) in share]
        elif not todo and is_done(folder) and not sources[1:]:
            # (with parts there, their rows -- of models finished after this evaluation -- are merged below)
            print(f"[evaluate] skipped, already evaluated in {folder}")
            return folder
        if len(todo) < len(jobs):
            print(f"[evaluate] {len(jobs) - len(todo)} model x task x split evaluation(s) kept, {len(todo)} to do -> {target}")
        jobs = todo
    for label, model, task, split in tqdm(jobs, desc="[evaluate]", unit="model x task x split", disable=not progress_bar):
        robots, count = robots_and_count(label, split)
        if label == "teacher-untrained":
            found = evaluate_untrained_teacher(profile, out, task, robots, count, profile.seed)
        else:
            # a curve played on the batched backend is not the single-env episodes of this table:
            # reused only where the run's model is not here to play them again
            reusable = label.startswith("transfer-") and (profile.transfer.eval_backend == "single" or not has_model(model))
            found = final_evaluation(model, split, robots, count) if reusable else None
            if found is None:
                found = evaluate_model(
                    model,
                    task,
                    robots,
                    count,
                    profile.max_episode_steps,
                    profile.seed,
                    instruction=run_instruction(profile, model, task) if label.startswith("transfer-") else None,
                    env_kwargs=profile_env_kwargs(profile),
                )
        seed = job_key(label, model, task, split)[3]
        rows += [{"model": label, "task": task, "split": split, "seed": seed, **row} for row in found]
        if not selected:  # an interruption loses at most the (model, task, split) under way
            write_rows(target, rows)
    write_rows(target, rows)
    if part is not None:
        print(f"[evaluate] part {part[0]}/{part[1]}: {len(jobs)} model x task x split evaluation(s) -> {target}")
        return folder
    if selected:
        print(f"[evaluate] {len(jobs)} model x task x split evaluation(s), {episodes} episode(s) per robot -> {folder}")
        return folder
    if has_model(student_folder(out)):  # (a skipped student has no gates)
        gates = student_gates(out, [r for robots in splits_robots.values() for r in robots], profile.seed, **profile_env_kwargs(profile))
        atomic_save(folder / "gates.npz", lambda p: np.savez(p, **gates))
    mark_done(folder, rows=len(rows))
    shutil.rmtree(folder / PARTS, ignore_errors=True)  # merged into returns.csv
    return folder


def write_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, buffer.getvalue())
    path.with_name(path.name + ".gz").unlink(missing_ok=True)  # the packed twin it replaces


def job_key(label: str, model: Path, task: str, split: str) -> tuple[str, str, str, str]:
    """``(model label, task, split, seed)`` of an evaluation job; the seed tells a transfer arm's runs
    apart (``""`` for the other models: one run each)."""
    if not label.startswith("transfer-"):
        return label, task, split, ""
    name = Path(model).name  # seed-<n>/, or the arm's folder itself for a run without seed folders (seed 0)
    return label, task, split, name.removeprefix("seed-") if name.startswith("seed-") else "0"


def row_key(row: dict[str, Any]) -> tuple[str, str, str, str]:
    """The :func:`job_key` of a ``returns.csv`` row (``seed`` is missing from files written before it was)."""
    return row["model"], row["task"], row["split"], str(row.get("seed") or "")


def complete_rows(sources: list[Path], expected: dict[tuple[str, str, str, str], tuple[list[Path], int]]) -> list[dict[str, str]]:
    """The rows of ``sources`` for each job (:func:`job_key`) of ``expected`` that has exactly its
    robots x episodes (the first source that has them wins; partial or stale ones are dropped), and
    those of the first source for a model that is not expected at all (a model no longer in this
    checkout keeps its rows; rows of an expected model under another key -- a transfer arm's seeds
    pooled before the seed column -- are evaluated again instead)."""
    models = {(key[0], key[1], key[2]) for key in expected}
    kept: dict[tuple[str, str, str, str], list[dict[str, str]]] = {}
    for source in sources:
        found: dict[tuple[str, str, str, str], list[dict[str, str]]] = {}
        for row in read_csv_rows(source):
            found.setdefault(row_key(row), []).append(row)
        for key, rows in found.items():
            if key in kept:
                continue
            if key not in expected:
                if source == sources[0] and key[:3] not in models:
                    kept[key] = rows
                continue
            robots, episodes = expected[key]
            if sorted((row["morphology"], int(row["episode"])) for row in rows) == sorted(
                (r.stem, e) for r in robots for e in range(episodes)
            ):
                kept[key] = rows
    return [row for rows in kept.values() for row in rows]
