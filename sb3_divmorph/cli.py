"""``divmorph``: the knowledge-diversion pipeline from the command line.

    divmorph pipeline --profile demo                 # every stage, in order (runs/demo)
    divmorph teachers --profile demo [--task FT]     # one MetaMorph teacher per training task
    divmorph distill  --profile demo                 # DAgger into the DivMorph student
    divmorph hyperdistill --profile demo             # baseline: HyperDistill student + per-robot MLPs
    divmorph transfer --profile demo --task Escape [--no-scratch]
    divmorph export   --profile demo --morphology train-000 --task FT
    divmorph evaluate --profile demo
    divmorph report   --profile demo
    divmorph record   runs/demo/teachers/FT              # MP4 of a pipeline or rl-zoo model, headless
    divmorph profiles [--profile demo]                   # the profiles and where they are read from

Every stage reads the profile (``zoo_configs/divmorph.yml``, shipped with the package, so any
working directory will do) and works in ``--out`` (default ``runs/<profile>``); finished stages
are skipped, interrupted ones resume.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="divmorph", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    def command(name: str, help_text: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--profile", default="demo", help="profile name in the profiles file (default: demo)")
        p.add_argument("--profiles", default="zoo_configs/divmorph.yml", help="profiles file (default: the shipped one)")
        p.add_argument("--out", default=None, help="run folder (default: runs/<profile>)")
        p.add_argument("--no-progress", action="store_true", help="no progress bars")
        return p

    command("pipeline", "run every stage in order")
    p = command("teachers", "train one MetaMorph teacher per training task (PPO)")
    p.add_argument("--task", action="append", help="only this training task (repeatable)")
    command("distill", "DAgger distillation of the teachers into a DivMorph student")
    command("hyperdistill", "HyperDistill baseline: distil the teachers into a hypernetwork student, export per-robot MLPs")
    p = command("transfer", "transfer the student to a novel task (and train MetaMorph from scratch)")
    p.add_argument("--task", action="append", help="novel task (repeatable; default: the profile's)")
    p.add_argument("--no-scratch", action="store_true", help="skip the from-scratch comparison")
    p = command("export", "prune + merge the student into a compact actor (ONNX and/or TorchScript)")
    p.add_argument("--morphology", action="append", help="robot name in the train/novel sets, or an MJCF path")
    p.add_argument("--task", action="append", help="task (default: the profile's)")
    p.add_argument("--format", choices=("onnx", "torchscript", "all"), default="all",
                   help="onnx (runs with onnxruntime + numpy), torchscript (torch alone), or all (default)")
    command("evaluate", "per-morphology returns on train and novel robots")
    command("report", "plots and a markdown summary of the run")

    # Commands that read no run: they take no --out and create nothing but what they write.
    from sb3_divmorph.record import add_arguments as record_arguments

    help_text = "record a trained model (pipeline stage or rl-zoo run) to MP4, headless"
    record_arguments(sub.add_parser("record", help=help_text, description=help_text))
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


def _robot_path(name: str) -> Path:
    from unimal_envs.morphology.loader import morphology_files

    path = Path(name)
    if path.suffix == ".xml":
        if not path.is_file():
            raise FileNotFoundError(f"MJCF file {path} does not exist")
        return path
    for split in ("train", "novel"):
        for file in morphology_files(split):
            if file.stem == name:
                return file
    raise ValueError(f"unknown morphology {name!r}: give a robot of the train/novel sets (e.g. train-000) or an MJCF path")


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "record":
        from sb3_divmorph.record import run as record

        return record(args)
    if args.command == "profiles":
        return _profiles(args)
    import torch as th

    from sb3_divmorph import pipeline as P
    from sb3_divmorph.pipeline.runs import record_robot_sets, seed_everything

    try:
        profile = P.load_profile(args.profile, args.profiles)
    except P.ConfigError as error:
        print(f"divmorph: {error}", file=sys.stderr)
        return 2
    out = Path(args.out or f"runs/{profile.name}")
    out.mkdir(parents=True, exist_ok=True)
    seed_everything(profile.seed, profile.torch_threads)
    progress = not args.no_progress
    command_line = "divmorph " + shlex.join(argv if argv is not None else sys.argv[1:])
    start = time.perf_counter()
    try:
        record_robot_sets(profile, out)  # out/robot_sets.json: which robots this run uses
        if args.command == "pipeline":
            print(P.run_pipeline(profile, out, progress, command_line))
        elif args.command == "teachers":
            P.train_teachers(profile, out, args.task, progress)
        elif args.command == "distill":
            P.distill(profile, out, progress)
        elif args.command == "hyperdistill":
            for r in P.hyperdistill(profile, out, progress):
                print(f"{r['robot']} x {r['task']}: MLP of {r['mlp_weights']:,} weights, max |diff| {r['max_abs_diff']:.1e}, "
                      f"latency {r['latency_mlp_ms']:.3f} ms -> {Path(out) / 'hyperdistill' / 'export'}")
        elif args.command == "transfer":
            P.transfer(profile, out, args.task, False if args.no_scratch else None, progress)
        elif args.command == "export":
            robots = [_robot_path(m) for m in args.morphology] if args.morphology else None
            formats = ("onnx", "torchscript") if args.format == "all" else (args.format,)
            for r in P.export_all(profile, out, args.task, robots, formats):
                print(f"{r['robot']} x {r['task']}: {r['compact_weights']:,} weights "
                      f"({r['reduction_vs_metamorph']:.1f}x smaller than MetaMorph's actor through the same folding), "
                      f"max |diff| {r['max_abs_diff']:.1e}, "
                      f"latency {r['latency_compact_ms']:.3f} ms vs {r['latency_student_ms']:.3f} ms -> {Path(out) / 'export'}")
        elif args.command == "evaluate":
            print(f"returns -> {P.evaluate(profile, out, progress) / 'returns.csv'}")
        elif args.command == "report":
            print(P.report(profile, out, command_line))
    except (P.ConfigError, FileNotFoundError, ValueError, KeyError, TypeError) as error:
        print(f"divmorph {args.command}: {error}", file=sys.stderr)
        return 2
    print(f"[divmorph] {args.command} finished in {time.perf_counter() - start:.0f} s (threads: {th.get_num_threads()}); outputs in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
