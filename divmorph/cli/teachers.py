"""``divmorph teachers``: one MetaMorph teacher per training task (PPO)."""

from __future__ import annotations

import argparse

from divmorph.cli.run_folder import add_grid_options, add_run_options, run_on_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_options(parser)
    add_grid_options(parser)
    parser.add_argument("--task", action="append", help="only this training task (repeatable)")


def _work(profile, out, args, progress, backend, command_line) -> None:
    from divmorph.pipeline.teachers import train_teachers

    train_teachers(profile, out, args.task, progress, backend=backend)


def run(args: argparse.Namespace) -> int:
    return run_on_folder(args, _work)
