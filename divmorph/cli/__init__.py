"""``divmorph``: the knowledge-diversion pipeline from the command line.

    divmorph pipeline --profile demo                 # every stage, in order (runs/demo)
    divmorph teachers --profile demo [--task FT]     # one MetaMorph teacher per training task
    divmorph distill  --profile demo [--arms A,B]    # DAgger into the DivMorph student (+ the arms' students)
    divmorph hyperdistill --profile demo             # baseline: HyperDistill student + per-robot MLPs
    divmorph grl      --profile demo                 # baseline: GRL's evolved learngene (whole layers)
    divmorph transfer --profile demo --task Escape --arms divmorph,scratch,closest --seeds 0 1 2
    divmorph export   --profile demo --morphology train-000 --task FT
    divmorph evaluate --profile demo
    divmorph evaluate --run runs/demo --model teacher --task FT --split train --episodes 3 --into my-eval
    divmorph report   --profile demo                 # summary.md + every figure with data
    divmorph figure transfer-train --profile demo    # one figure (PNG + CSV) in report/figures/
    divmorph record   runs/demo/teachers/FT              # MP4 of a pipeline or rl-zoo model, headless
    divmorph plot     logs/ppo/Unimal-FT-v0_1            # learning curves of rl-zoo runs or stages, PNG, headless
    divmorph profiles [--profile demo]                   # the profiles and where they are read from
    divmorph branch --from runs/demo --out runs/demo-long  # a new run reusing demo's teachers and students
    divmorph migrate runs/old-run                        # a run.json of record format 1, in today's keys

Every stage reads the profile (``zoo_configs/divmorph.yml``, shipped with the package, so any
working directory will do) and works in ``--out`` (default ``runs/<profile>``); finished stages
are skipped, interrupted ones resume. The trainings of ``pipeline``, ``teachers``, ``distill``,
``grl`` and ``transfer`` are independent runs of a grid: ``--backend ray`` runs them as Ray tasks
(a local Ray by default, a cluster with ``--address``).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

#: ``command: (module, one-line help)``. A command's module has ``add_arguments(parser)`` and
#: ``run(args) -> exit status``; it is imported only when its command runs, so the overview
#: (``divmorph --help``) imports neither the library nor torch.
COMMANDS: dict[str, tuple[str, str]] = {
    "pipeline": ("divmorph.cli.pipeline", "run every stage in order"),
    "teachers": ("divmorph.cli.teachers", "train one MetaMorph teacher per training task (PPO)"),
    "distill": (
        "divmorph.cli.distill",
        "DAgger distillation of the teachers into the DivMorph student (and the students of the arms)",
    ),
    "hyperdistill": (
        "divmorph.cli.hyperdistill",
        "HyperDistill baseline: distil the teachers into a hypernetwork student, export per-robot MLPs",
    ),
    "grl": (
        "divmorph.cli.grl",
        "GRL baseline: evolve a population of MetaMorph agents; the best learngene (whole layers) for the grl arm",
    ),
    "transfer": ("divmorph.cli.transfer", "race the transfer arms on novel tasks (arms x tasks x seeds, one run each)"),
    "export": ("divmorph.cli.export", "prune + merge the student into a compact actor (ONNX and/or TorchScript)"),
    "evaluate": ("divmorph.cli.evaluate", "per-morphology returns on train and novel robots"),
    "report": ("divmorph.cli.report", "plots, the paper's figures and a markdown summary of the run"),
    "figure": ("divmorph.cli.figure", "one of the paper's figures (PNG + CSV in report/figures/)"),
    "record": ("divmorph.record", "record a trained model (pipeline stage or rl-zoo run) to MP4, headless"),
    "plot": (
        "divmorph.plot",
        "learning curves of rl-zoo runs (Monitor files) or pipeline stages (progress.csv) as a PNG, headless",
    ),
    "fetch-models": (
        "divmorph.cli.fetch_models",
        "copy a shipped run's trained models (e.g. cpu100) into the local cache, checked, for a pip install",
    ),
    "branch": ("divmorph.cli.branch", "start a run folder that reuses another run's finished teachers, students and GRL learngene"),
    "migrate": ("divmorph.cli.migrate", "rewrite the run.json of run folders recorded before divmorph 0.2 in today's keys"),
    "profiles": ("divmorph.cli.profiles", "list the profiles (or print one, validated) and the file they are read from"),
}


def version() -> str:
    """The installed package's version (``unknown`` when run from a tree that is not installed)."""
    from importlib import metadata

    try:
        return metadata.version("divmorph")
    except metadata.PackageNotFoundError:
        return "unknown"


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser: every command with its one-line help, and the arguments of
    ``command`` (``None``: of every command; the overview passes an unknown name, e.g. ``""``).
    """
    parser = argparse.ArgumentParser(prog="divmorph", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"divmorph {version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if command is None or command == name:
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one ``divmorph`` command (``argv``: its arguments, default ``sys.argv[1:]``); the exit status."""
    words = sys.argv[1:] if argv is None else list(argv)
    # only the command asked for builds its arguments: the overview imports nothing of the library
    args = build_parser(command=words[0] if words else "").parse_args(words)
    args.argv = words  # the command line, recorded by the commands that write a run folder
    return importlib.import_module(COMMANDS[args.command][0]).run(args)
