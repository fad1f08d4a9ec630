"""``divmorph``: the knowledge-diversion pipeline from the command line.

    divmorph pipeline --profile demo                 # every stage, in order (runs/demo)
    divmorph teachers --profile demo [--task FT]     # one MetaMorph teacher per training task
    divmorph distill  --profile demo [--arms A,B]    # DAgger into the DivMorph student (+ the arms' students)
    divmorph hyperdistill --profile demo             # baseline: HyperDistill student + per-robot MLPs
    divmorph grl      --profile demo                 # baseline: GRL's evolved learngene (whole layers)
    divmorph transfer --profile demo --task Escape --arms divmorph,scratch,closest --seeds 0 1 2
    divmorph export   --profile demo --morphology train-000 --task FT
    divmorph evaluate --profile demo
    divmorph evaluate --run results/cpu --model teacher --task FT --split train --episodes 3 --into my-eval
    divmorph report   --profile demo                 # summary.md + every figure with data
    divmorph figure transfer-train --profile demo    # one figure (PNG + CSV) in report/figures/
    divmorph record   runs/demo/teachers/FT              # MP4 of a pipeline or rl-zoo model, headless
    divmorph plot     logs/ppo/Unimal-FT-v0_1            # learning curves of rl-zoo runs or stages, PNG, headless
    divmorph profiles [--profile demo]                   # the profiles and where they are read from
    divmorph branch --from runs/demo --out runs/demo-long  # a new run reusing demo's teachers and students

Every stage reads the profile (``zoo_configs/divmorph.yml``, shipped with the package, so any
working directory will do) and works in ``--out`` (default ``runs/<profile>``); finished stages
are skipped, interrupted ones resume. The trainings of ``pipeline``, ``teachers``, ``distill``,
``grl`` and ``transfer`` are independent runs of a grid: ``--backend ray`` runs them as Ray tasks
(a local Ray by default, a cluster with ``--address``).
"""

from __future__ import annotations

import argparse
import os
import shlex
import signal
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


def _parser(overview: bool = False) -> argparse.ArgumentParser:
    """The command line's parser.

    :param overview: the parser of ``divmorph`` / ``divmorph --help`` alone: every command with its
        one-line help but without the arguments whose help is read from the library (the arms, the
        reusable stages, ``record``'s and ``plot``'s options), so that the overview imports neither
        ``sb3_divmorph`` nor torch (seconds saved on every ``--help``).
    """
    parser = argparse.ArgumentParser(prog="divmorph", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"divmorph {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    def command(name: str, help_text: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text)
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
            help="the settings differ from the run's (run.json): retrain every begun stage they touch "
            "(old folders kept in <out>/superseded/)",
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
        return p

    def grid(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
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
        return p

    def arms_list(text: str) -> list[str]:
        return [a.strip() for a in text.split(",") if a.strip()]

    grid(command("pipeline", "run every stage in order"))
    p = grid(command("teachers", "train one MetaMorph teacher per training task (PPO)"))
    p.add_argument("--task", action="append", help="only this training task (repeatable)")
    p = grid(command("distill", "DAgger distillation of the teachers into the DivMorph student (and the students of the arms)"))
    p.add_argument("--arms", type=arms_list, default=None, help="also distil the students these arms start from (comma-separated)")
    p.add_argument(
        "--students",
        type=arms_list,
        default=None,
        help="distil exactly these students (comma-separated; see `sb3_divmorph.pipeline.students.STUDENTS`), e.g. deploy-g1k1",
    )
    command("hyperdistill", "HyperDistill baseline: distil the teachers into a hypernetwork student, export per-robot MLPs")
    grid(command("grl", "GRL baseline: evolve a population of MetaMorph agents; the best learngene (whole layers) for the grl arm"))
    p = grid(command("transfer", "race the transfer arms on novel tasks (arms x tasks x seeds, one run each)"))
    p.add_argument("--task", action="append", help="novel task (repeatable; default: the profile's)")
    if not overview:
        from sb3_divmorph.pipeline.arms import ARMS

        p.add_argument(
            "--arms",
            type=arms_list,
            default=None,
            help="comma-separated arms (default: the profile's transfer.arms), of: "
            + "; ".join(f"{name} ({arm.label})" for name, arm in ARMS.items()),
        )
    p.add_argument("--seeds", type=int, nargs="+", default=None, help="seeds, one run each (default: the profile's transfer.seeds)")
    p.add_argument(
        "--closest-by",
        choices=("embedding", "return"),
        default=None,
        help="closest arm: most similar instruction embedding (default) or best zero-shot teacher return",
    )
    p.add_argument("--no-scratch", action="store_true", help="leave scratch out of the default arms")
    p = command("export", "prune + merge the student into a compact actor (ONNX and/or TorchScript)")
    p.add_argument("--morphology", action="append", help="robot name in the train/novel sets, or an MJCF path")
    p.add_argument("--task", action="append", help="task (default: the profile's)")
    p.add_argument(
        "--format",
        choices=("onnx", "torchscript", "all"),
        default="all",
        help="onnx (runs with onnxruntime + numpy), torchscript (torch alone), or all (default)",
    )
    p.add_argument(
        "--student",
        action="append",
        help="distilled DivMorph student to deploy (repeatable; default: divmorph and every finished deploy-* student)",
    )
    p = command("evaluate", "per-morphology returns on train and novel robots")
    p.add_argument(
        "source",
        nargs="?",
        default=None,
        help="instead of a run: one model folder (a pipeline stage, an rl-zoo run folder or a .zip), evaluated on "
        "the robots and env settings it was trained with (or --robots), its returns printed and written to --into",
    )
    p.add_argument("--robots", default=None, help="with a model folder: a robot set, folder or name (default: its own robots)")
    p.add_argument(
        "--model",
        action="append",
        dest="models",
        help="only this model label (repeatable): teacher, teacher-untrained, student, student-<name>, hyperdistill, transfer-<arm>",
    )
    p.add_argument("--task", action="append", dest="eval_tasks", help="only this task (repeatable)")
    p.add_argument(
        "--split",
        action="append",
        dest="splits",
        choices=("train", "novel", "ood"),
        help="only these robots (repeatable; ood: the profile's out-of-distribution set)",
    )
    p.add_argument("--episodes", type=int, default=None, help="episodes per robot (default: the profile's evaluate.episodes)")
    p.add_argument(
        "--into",
        type=Path,
        default=None,
        help="folder for the selection's returns.csv (default: evaluations/<run>-<time>/ here); a selection never "
        "writes into the run's evaluate/",
    )
    p.add_argument(
        "--part",
        type=_part,
        default=None,
        metavar="K/N",
        help="evaluate the k-th of n shares of the run's evaluation (n processes, one per core); a plain evaluate "
        "afterwards merges them and finishes",
    )
    command("report", "plots, the paper's figures and a markdown summary of the run")
    p = command("figure", "one of the paper's figures (PNG + CSV in report/figures/)")
    p.add_argument("name", help="transfer-train, transfer-novel, deployment, pareto, ablation or gates")

    # Commands that read no run: they take no --out and create nothing but what they write.
    help_text = "record a trained model (pipeline stage or rl-zoo run) to MP4, headless"
    p = sub.add_parser("record", help=help_text, description=help_text)
    if not overview:
        from sb3_divmorph.record import add_arguments as record_arguments

        record_arguments(p)
    help_text = "learning curves of rl-zoo runs (Monitor files) or pipeline stages (progress.csv) as a PNG, headless"
    p = sub.add_parser("plot", help=help_text, description=help_text)
    if not overview:
        from sb3_divmorph.plot import add_arguments as plot_arguments

        plot_arguments(p)
    help_text = "copy a shipped run's trained models (e.g. cpu100) into the local cache, checked, for a pip install"
    p = sub.add_parser("fetch-models", help=help_text, description=help_text)
    p.add_argument("run", help="the shipped run (cpu100: the 100-robot run's teachers and students)")
    p.add_argument(
        "--source",
        required=True,
        help="a checkout of the divmorph repository, a .tar.gz archive of it, or the URL of such an archive",
    )
    p.add_argument("--cache", default=None, help="the cache folder (default $DIVMORPH_MODELS, else ~/.cache/divmorph/models)")
    p.add_argument("--force", action="store_true", help="fetch again even if already cached")
    help_text = "start a run folder that reuses another run's finished teachers, students and GRL learngene"
    p = sub.add_parser("branch", help=help_text, description=help_text)
    if not overview:
        from sb3_divmorph.pipeline.branch import REUSABLE_STAGES

        p.add_argument("--from", dest="source", required=True, help="the run folder whose finished stages are reused")
        p.add_argument("--out", "--run", required=True, help="the new run folder (must not exist or be empty)")
        p.add_argument(
            "--stages",
            type=arms_list,
            default=list(REUSABLE_STAGES),
            help=f"comma-separated stages to reuse (default: {','.join(REUSABLE_STAGES)})",
        )
    help_text = "list the profiles (or print one, validated) and the file they are read from"
    p = sub.add_parser("profiles", help=help_text, description=help_text)
    p.add_argument("--profile", help="print this profile's settings")
    p.add_argument("--profiles", default="zoo_configs/divmorph.yml", help="profiles file (default: the shipped one)")
    return parser


def _profiles(args: argparse.Namespace) -> int:
    """``divmorph profiles``: the profile names (or one profile, validated) and their file."""
    import dataclasses

    import yaml

    from sb3_divmorph.pipeline.config import ConfigError, load_profile, load_profiles, resolve_path

    try:
        names = sorted(load_profiles(args.profiles))
        if args.profile is not None:
            settings = dataclasses.asdict(load_profile(args.profile, args.profiles))
    except ConfigError as error:
        print(f"divmorph: {error}", file=sys.stderr)
        return 2
    print(f"# {resolve_path(args.profiles).resolve()}")
    print(yaml.safe_dump({args.profile: settings}, sort_keys=False) if args.profile is not None else "\n".join(names))
    return 0


def _branch(args: argparse.Namespace, argv: list[str] | None) -> int:
    """``divmorph branch``: a new run folder linking another run's finished stages."""
    from sb3_divmorph.pipeline.branch import branch
    from sb3_divmorph.pipeline.config import ConfigError

    command_line = "divmorph " + shlex.join(argv if argv is not None else sys.argv[1:])
    try:
        links = branch(Path(args.source), Path(args.out), args.stages, command_line)
    except (ConfigError, FileNotFoundError) as error:
        print(f"divmorph branch: {error}", file=sys.stderr)
        return 2
    for link in links:
        print(f"{link} -> {os.readlink(link)}")
    print(
        f"[divmorph] branch: {len(links)} finished runs of {args.source} reused in {args.out}; run the later stages there "
        f"with --run {args.out} (and --set KEY=VALUE for their new settings)"
    )
    return 0


def _part(text: str) -> tuple[int, int]:
    """``"k/n"`` (``--part``) as ``(k, n)`` with 1 <= k <= n."""
    try:
        k, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a part is K/N, e.g. 1/2, got {text!r}") from None
    if not 1 <= k <= n:
        raise argparse.ArgumentTypeError(f"a part K/N needs 1 <= K <= N, got {text!r}")
    return k, n


def _evaluate_model_folder(args: argparse.Namespace) -> int:
    """``divmorph evaluate FOLDER``: any saved model, on its own robots and settings (``load_pretrained``)."""
    import csv

    import torch as th

    from sb3_divmorph.pretrained import PretrainedError, load_pretrained

    th.set_num_threads(1)
    if args.episodes is not None and args.episodes < 1:
        print(f"divmorph evaluate: --episodes must be at least 1, got {args.episodes}", file=sys.stderr)
        return 2
    tasks = args.eval_tasks or [None]
    try:
        model = load_pretrained(args.source)
        rows = []
        for task in tasks:
            found = model.evaluate(args.robots, task=task, episodes=args.episodes or 1, seed=args.seed or 0)
            rows += [{"model": str(args.source), "task": task or (model.env_id or "").split("-")[1], **row} for row in found]
    except (PretrainedError, ValueError, FileNotFoundError) as error:
        print(f"divmorph evaluate: {error}", file=sys.stderr)
        return 2
    for row in sorted(rows, key=lambda r: (r["task"], r["robot"], r["episode"])):
        print(f"{row['task']} {row['robot']} episode {row['episode']}: return {row['return']:.1f} over {row['length']} steps")
    means = {task: [r["return"] for r in rows if r["task"] == task] for task in dict.fromkeys(r["task"] for r in rows)}
    for task, values in means.items():
        print(f"{task}: mean return {sum(values) / len(values):.1f} over {len(values)} episodes")
    if args.into is not None:
        args.into.mkdir(parents=True, exist_ok=True)
        with open(args.into / "returns.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=["model", "task", "robot", "episode", "return", "length"])
            writer.writeheader()
            writer.writerows(rows)
        print(f"-> {args.into / 'returns.csv'}")
    return 0


def _version() -> str:
    """The installed package's version (``unknown`` when run from a tree that is not installed)."""
    from importlib import metadata

    try:
        return metadata.version("divmorph")
    except metadata.PackageNotFoundError:
        return "unknown"


def _robot_path(name: str, profile=None) -> Path:
    """A robot by MJCF path, or by name among the profile's robots (every split), else the shipped sets."""
    from sb3_divmorph.pipeline.robots import profile_robots, profile_splits
    from unimal_envs.morphology.loader import morphology_files

    path = Path(name)
    if path.suffix == ".xml":
        if not path.is_file():
            raise FileNotFoundError(f"MJCF file {path} does not exist")
        return path
    candidates = [(split, lambda split=split: profile_robots(profile, split)) for split in profile_splits(profile)] if profile else []
    candidates += [(split, lambda split=split: morphology_files(split)) for split in ("train", "novel")]
    for _, files in candidates:
        for file in files():
            if file.stem == name:
                return file
    where = "the run's robots or " if profile else ""
    raise ValueError(f"unknown morphology {name!r}: give a robot of {where}the train/novel sets (e.g. train-000) or an MJCF path")


def _overrides(args: argparse.Namespace) -> dict:
    """The profile overrides given on the command line (``--seed``, ``--device``, robots, ``--set``)."""
    from sb3_divmorph.pipeline.config import parse_override

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


#: Commands that read the stages of an existing run (a missing --run folder is a typo, not a new run).
_READS_A_RUN = ("evaluate", "report", "export", "figure")


def _put_back(out: Path, record: dict, previous_record: str | None) -> None:
    """After a failed command, the stage folders its --redo/--force had moved aside go back."""
    from sb3_divmorph.pipeline.provenance import restore_superseded

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


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C raises KeyboardInterrupt, so that both stop a command the same way."""


def _fetch_models(args: argparse.Namespace) -> int:
    from sb3_divmorph.shipped import ShippedModelsError, fetch_models

    try:
        folder = fetch_models(args.run, args.source, cache=args.cache, force=args.force)
    except ShippedModelsError as error:
        print(f"divmorph fetch-models: {error}", file=sys.stderr)
        return 2
    print(f'{args.run}: its models in {folder}; load_pretrained("results/{args.run}/teachers/FT") now finds them from any folder')
    return 0


def _terminate(signum: int, frame: object) -> None:
    raise Terminated


def main(argv: list[str] | None = None) -> int:
    """Run one ``divmorph`` command (``argv``: its arguments, default ``sys.argv[1:]``); the exit status."""
    words = sys.argv[1:] if argv is None else argv
    # the overview (no command, or --help before any command) is answered without importing the library
    args = _parser(overview=not words or words[0] in ("-h", "--help")).parse_args(argv)
    if args.command == "record":
        from sb3_divmorph.record import run as run_record

        return run_record(args)
    if args.command == "plot":
        from sb3_divmorph.plot import run as plot

        return plot(args)
    if args.command == "evaluate" and args.source is not None:
        return _evaluate_model_folder(args)
    if args.command == "profiles":
        return _profiles(args)
    if args.command == "fetch-models":
        return _fetch_models(args)
    if args.command == "branch":
        return _branch(args, argv)
    import torch as th

    from sb3_divmorph import pipeline as P
    from sb3_divmorph.pipeline.provenance import check_and_record
    from sb3_divmorph.pipeline.envs import seed_everything
    from sb3_divmorph.pipeline.robots import record_robot_sets

    try:
        recorded = Path(args.out) / "run.json" if args.out and args.profile is None else None
        if recorded is not None and recorded.is_file():
            # a run is described by its records: the configuration it was run with, not today's profiles file
            profile = P.recorded_profile(recorded, _overrides(args))
        else:
            profile = P.load_profile(args.profile or "demo", args.profiles, _overrides(args))
    except P.ConfigError as error:
        print(f"divmorph: {error}", file=sys.stderr)
        return 2
    out = Path(args.out or f"runs/{profile.name}")
    if args.command == "figure" and args.name not in P.FIGURES:  # a typo in the name, before anything about the run
        print(f"divmorph figure: unknown figure {args.name!r}; figures: {list(P.FIGURES)}", file=sys.stderr)
        return 2
    if args.command in _READS_A_RUN and args.out and not out.is_dir():
        print(
            f"divmorph {args.command}: no such run folder: {out} (train its stages with --out {out} first, or check the path)",
            file=sys.stderr,
        )
        return 2
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    seed_everything(profile.seed, profile.torch_threads)
    progress = not args.no_progress
    command_line = "divmorph " + shlex.join(argv if argv is not None else sys.argv[1:])
    start = time.perf_counter()
    record: dict | None = None
    previous_record: str | None = None
    # SIGTERM (`kill`, `timeout`'s default, a scheduler's preemption) stops a command as Ctrl-C does:
    # a run in training saves a checkpoint where it stopped (TrainingRun) before the command exits
    on_main_thread = threading.current_thread() is threading.main_thread()
    previous_sigterm = signal.signal(signal.SIGTERM, _terminate) if on_main_thread else None
    try:
        # out/run.json: the configuration, robots, versions, commit and device of this run; a run
        # is only continued with the settings it was started with (unless --force)
        # An evaluation of a selection only reads the run: its records stay as they are.
        reads_only = args.command == "evaluate" and any(
            getattr(args, k) is not None for k in ("models", "eval_tasks", "splits", "episodes", "into")
        )
        if not reads_only:
            previous_record = (out / "run.json").read_text() if (out / "run.json").is_file() else None
            record = check_and_record(out, profile, command_line, args.force, args.redo, args.extend)
            record_robot_sets(profile, out)  # out/robot_sets.json: which robots this run uses
        backend = None
        if getattr(args, "backend", None) is not None:
            if args.backend == "local" and (args.cpus_per_run != 1 or args.gpus_per_run != 0 or args.ray_cpus is not None):
                raise P.ConfigError("--cpus-per-run / --gpus-per-run / --ray-cpus need --backend ray")
            backend = P.make_backend(args.backend, args.address, args.cpus_per_run, args.gpus_per_run, args.ray_cpus)
        if args.command == "pipeline":
            print(P.run_pipeline(profile, out, progress, command_line, backend))
        elif args.command == "teachers":
            P.train_teachers(profile, out, args.task, progress, backend=backend)
        elif args.command == "distill":
            from sb3_divmorph.pipeline.arms import students_for
            from sb3_divmorph.pipeline.config import check_arms

            if args.arms is not None and args.students is not None:
                raise P.ConfigError("give --arms or --students, not both")
            if args.arms is not None:
                check_arms(args.arms, "--arms")
            students = args.students if args.arms is None else ["divmorph", *students_for(args.arms)]
            P.distill(profile, out, progress, students, backend)
        elif args.command == "grl":
            learngene = P.evolve(profile, out, backend, progress)
            print(
                f"learngene: {'+'.join(learngene['units'])} (agent {learngene['agent']} of generation {learngene['generation']}, "
                f"{learngene['task']}) -> {Path(out) / 'grl' / 'learngene.json'}"
            )
        elif args.command == "figure":
            path = P.make_figure(profile, out, args.name)
            if path is None:
                raise FileNotFoundError(f"no data for figure {args.name!r} in {out} yet (run the stages it plots first)")
            print(f"{args.name} -> {path} (numbers: {path.with_suffix('.csv')})")
        elif args.command == "hyperdistill":
            for r in P.hyperdistill(profile, out, progress):
                print(
                    f"{r['robot']} x {r['task']}: MLP of {r['mlp_weights']:,} weights, max |diff| {r['max_abs_diff']:.1e}, "
                    f"latency {r['latency_mlp_ms']:.3f} ms -> {Path(out) / 'hyperdistill' / 'export'}"
                )
        elif args.command == "transfer":
            P.transfer(
                profile, out, args.task, False if args.no_scratch else None, progress, args.arms, args.seeds, backend, args.closest_by
            )
        elif args.command == "export":
            robots = [_robot_path(m, profile) for m in args.morphology] if args.morphology else None
            formats = ("onnx", "torchscript") if args.format == "all" else (args.format,)
            for r in P.export_all(profile, out, args.task, robots, formats, args.student):
                print(
                    f"{r['student']}: {r['robot']} x {r['task']}: {r['compact_weights']:,} weights "
                    f"({r['reduction_vs_metamorph']:.1f}x smaller than MetaMorph's actor through the same folding), "
                    f"max |diff| {r['max_abs_diff']:.1e}, "
                    f"latency {r['latency_compact_ms']:.3f} ms vs {r['latency_student_ms']:.3f} ms, "
                    f"return {r['compact_return']:.1f} (student {r['student_return']:.1f})"
                )
        elif args.command == "evaluate":
            folder = P.evaluate(profile, out, progress, args.models, args.eval_tasks, args.splits, args.episodes, args.into, args.part)
            print(f"returns -> {folder / 'returns.csv'}")
        elif args.command == "report":
            print(P.report(profile, out, command_line))
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


if __name__ == "__main__":
    sys.exit(main())
