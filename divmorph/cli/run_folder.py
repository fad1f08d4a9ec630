"""What every command on a run folder shares: its options, the profile it runs with, and the
lifecycle of a command on the folder (records, interruption, putting superseded stages back)."""

from __future__ import annotations

import argparse
import shlex
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path


def add_run_options(parser: argparse.ArgumentParser) -> None:
    """The options of a command on a run folder (the profile, the folder, overrides, retraining)."""
    p = parser
    p.add_argument(
        "--profile", default=None, help="profile name in the profiles file (default: the one recorded in --out's run.json, else demo)"
    )
    p.add_argument("--profiles", default="zoo_configs/divmorph.yml", help="profiles file (default: the shipped one)")
    p.add_argument("--out", "--run", default=None, help="run folder (default: runs/<profile>)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--seed", type=int, default=None, help="override the profile's seed")
    p.add_argument("--device", default=None, help="override the profile's device (cpu, cuda, auto)")
    p.add_argument(
        "--train-robots",
        default=None,
        metavar="N|SET",
        help="override the training robots: a count, or a set (name or directory) used whole",
    )
    p.add_argument("--novel-robots", default=None, metavar="N|SET", help="override the novel robots likewise")
    p.add_argument(
        "--force",
        action="store_true",
        help="the settings differ from the run's (run.json): retrain every begun stage they touch (old folders kept in <out>/superseded/)",
    )
    p.add_argument(
        "--redo",
        action="append",
        default=[],
        metavar="STAGE",
        help="retrain this stage and the begun stages built on it (repeatable; teachers, distill, hyperdistill, "
        "grl, transfer, export, evaluate); old folders kept in <out>/superseded/",
    )
    p.add_argument(
        "--continue",
        dest="extend",
        action="append",
        default=[],
        metavar="STAGE",
        help="continue this stage's finished runs to a larger budget, from their final models (teachers or transfer; "
        "e.g. --continue teachers --set teachers.n_timesteps=16000000)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override any profile key, e.g. --set teachers.n_timesteps=5000 (repeatable; validated like the YAML)",
    )


def add_grid_options(parser: argparse.ArgumentParser) -> None:
    """The options of a command whose trainings are independent runs of a grid (local or Ray)."""
    p = parser
    p.add_argument(
        "--backend",
        choices=("local", "ray"),
        default="local",
        help="local: one run after the other in this process (default); ray: every run a Ray task",
    )
    p.add_argument("--address", default=None, help="Ray cluster address (host:port, ray://host:port or auto); default: a local Ray")
    p.add_argument("--cpus-per-run", type=float, default=1, help="CPUs Ray reserves per run (default 1)")
    p.add_argument("--gpus-per-run", type=float, default=0, help="GPUs (fractions allowed) Ray reserves per run (default 0)")
    p.add_argument("--ray-cpus", type=int, default=None, help="CPUs of the local Ray instance (default: all of this machine's)")


def arms_list(text: str) -> list[str]:
    """``"divmorph, scratch"`` -> ``["divmorph", "scratch"]`` (``--arms``, ``--students``, ``--stages``)."""
    return [a.strip() for a in text.split(",") if a.strip()]


def profile_overrides(args: argparse.Namespace) -> dict:
    """The profile overrides given on the command line (``--seed``, ``--device``, robots, ``--set``)."""
    from divmorph.pipeline.config import parse_override

    overrides = dict(parse_override(text) for text in args.set)
    if args.seed is not None:
        overrides["seed"] = args.seed
    if args.device is not None:
        overrides["device"] = args.device
    for split in ("train", "novel"):
        value = getattr(args, f"{split}_robots")
        if value is None:
            continue
        if value.isdigit():
            overrides[f"{split}_robots"] = int(value)
        else:  # a set name or directory, used whole
            overrides[f"{split}_set"], overrides[f"{split}_robots"] = value, None
    return overrides


def check_set_keys(texts: list[str]) -> str | None:
    """What is wrong with the first ``--set KEY=VALUE`` whose form or key name is not a profile's, or
    ``None`` (light: values are checked with the whole profile, later)."""
    from divmorph.pipeline.retired import REMOVED_KEYS
    from divmorph.profile import unknown_override

    for text in texts:
        key, sep, _ = text.partition("=")
        if not sep or not key.strip():
            return f"--set takes KEY=VALUE (e.g. teachers.n_timesteps=5000), got {text!r}"
        mistake = unknown_override(key.strip(), REMOVED_KEYS)
        if mistake is not None:
            return f"--set {text}: {mistake}"
    return None


def check_task_names(args: argparse.Namespace) -> str | None:
    """What is wrong with the command's ``--task`` names that are no task's, or ``None`` (which tasks
    suit the command is checked with the profile, later)."""
    from divmorph.profile import unknown_tasks

    tasks = getattr(args, "task", None) or getattr(args, "eval_tasks", None) or []
    return unknown_tasks(list(tasks))


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C raises KeyboardInterrupt, so that both stop a command the same way."""


def _terminate(signum: int, frame: object) -> None:
    raise Terminated


def _put_back(out: Path, record: dict, previous_record: str | None) -> None:
    """After a failed command, the stage folders its --redo/--force had moved aside go back."""
    from divmorph.pipeline.provenance import restore_superseded

    failed = restore_superseded(out, record, previous_record)
    if record["history"][-1].get("superseded"):
        print(
            f"divmorph: the previous {', '.join(record['history'][-1]['retrained'])} folders are back in {out}"
            + (f" (the failed attempt's output: {failed})" if failed else ""),
            file=sys.stderr,
        )


def _remove_if_untouched(out: Path) -> None:
    """Remove a run folder this command created when nothing but its records were written:
    a command that fails on its arguments leaves no empty run behind (and never deletes results)."""
    records = ("robot_sets.json", "run.json")
    if not [p for p in out.rglob("*") if p.name not in records]:
        for name in records:
            (out / name).unlink(missing_ok=True)
        out.rmdir()


#: ``work(profile, out, args, progress, backend, command_line)``: what a command does in its run folder
Work = Callable[..., None]


def run_on_folder(args: argparse.Namespace, work: Work, reads_a_run: bool = False, records: bool = True, trains: bool = True) -> int:
    """Run ``work`` in the command's run folder; the exit status.

    The profile is the one the folder's ``run.json`` records (a run is described by its records),
    else ``--profile`` from the profiles file. Before the work, ``run.json`` and ``robot_sets.json``
    are checked and written (a run continues only with the settings it started with, unless
    ``--force``). A failure puts back the stage folders ``--redo``/``--force`` had moved aside and
    removes a folder this command created and left empty; Ctrl-C and SIGTERM stop alike, after the
    training in progress saved a checkpoint.

    :param reads_a_run: the command reads an existing run: a missing ``--run`` folder is a typo.
    :param records: ``False`` for a command that only reads the run (its records stay as they are).
    :param trains: ``False`` for a command that trains nothing (it exports, evaluates or reports the
        finished stages): it may run on stages trained under retired rules.
    """
    # the command line's own mistakes are said before torch and the stages load (seconds, not half a minute)
    mistake = check_set_keys(args.set) or check_task_names(args)
    if mistake is not None:
        print(f"divmorph {args.command}: {mistake}", file=sys.stderr)
        return 2

    import torch as th

    from divmorph import pipeline as P
    from divmorph.pipeline.envs import seed_everything
    from divmorph.pipeline.provenance import check_and_record
    from divmorph.pipeline.robots import record_robot_sets

    try:
        recorded = Path(args.out) / "run.json" if args.out and args.profile is None else None
        if recorded is not None and recorded.is_file():
            profile = P.recorded_profile(recorded, profile_overrides(args))
        else:
            profile = P.load_profile(args.profile or "demo", args.profiles, profile_overrides(args))
    except P.ConfigError as error:
        print(f"divmorph: {error}", file=sys.stderr)
        return 2
    out = Path(args.out or f"runs/{profile.name}")
    if reads_a_run and args.out and not out.is_dir():
        print(
            f"divmorph {args.command}: no such run folder: {out} (train its stages with --out {out} first, or check the path)",
            file=sys.stderr,
        )
        return 2
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    seed_everything(profile.seed, profile.torch_threads)
    command_line = "divmorph " + shlex.join(getattr(args, "argv", None) or sys.argv[1:])
    start = time.perf_counter()
    record: dict | None = None
    previous_record: str | None = None
    # SIGTERM (`kill`, `timeout`'s default, a scheduler's preemption) stops a command as Ctrl-C does:
    # a run in training saves a checkpoint where it stopped (TrainingRun) before the command exits
    on_main_thread = threading.current_thread() is threading.main_thread()
    previous_sigterm = signal.signal(signal.SIGTERM, _terminate) if on_main_thread else None
    try:
        if records:
            previous_record = (out / "run.json").read_text() if (out / "run.json").is_file() else None
            record = check_and_record(out, profile, command_line, args.force, args.redo, args.extend, trains)
            record_robot_sets(profile, out)
        backend = None
        if getattr(args, "backend", None) is not None:
            if args.backend == "local" and (args.cpus_per_run != 1 or args.gpus_per_run != 0 or args.ray_cpus is not None):
                raise P.ConfigError("--cpus-per-run / --gpus-per-run / --ray-cpus need --backend ray")
            backend = P.make_backend(args.backend, args.address, args.cpus_per_run, args.gpus_per_run, args.ray_cpus)
        work(profile, out, args, not args.no_progress, backend, command_line)
    except (P.ConfigError, FileNotFoundError, ValueError, KeyError, TypeError) as error:
        print(f"divmorph {args.command}: {error}", file=sys.stderr)
        if record is not None:
            _put_back(out, record, previous_record)
        if created:
            _remove_if_untouched(out)
        return 2
    except P.GridError as error:
        print(f"divmorph {args.command}: {error}", file=sys.stderr)
        if record is not None:
            _put_back(out, record, previous_record)
        return 1
    except BaseException as error:  # anything else (a corrupted model file, Ctrl-C): put the good results back, then fail loudly
        if record is not None:
            _put_back(out, record, previous_record)
        if isinstance(error, KeyboardInterrupt):  # Ctrl-C, SIGTERM or a time limit's signal: not a bug, no traceback
            print(
                f"divmorph {args.command}: interrupted. A run that had trained since its last checkpoint saved one "
                "(an [interrupted] line above says where); the same command resumes unfinished runs from their latest checkpoint",
                file=sys.stderr,
            )
            return 128 + (signal.SIGTERM if isinstance(error, Terminated) else signal.SIGINT)
        raise
    finally:
        if previous_sigterm is not None:
            signal.signal(signal.SIGTERM, previous_sigterm)
    where = getattr(args, "into", None) or out  # a selection evaluated --into a folder leaves the run untouched
    print(
        f"[divmorph] {args.command} finished in {time.perf_counter() - start:.0f} s (threads: {th.get_num_threads()}); outputs in {where}"
    )
    return 0
