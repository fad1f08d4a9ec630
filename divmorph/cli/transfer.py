"""``divmorph transfer``: the transfer arms raced on novel tasks (arms x tasks x seeds, one run each)."""

from __future__ import annotations

import argparse

from divmorph.cli.run_folder import add_grid_options, add_run_options, arms_list, run_on_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from divmorph.pipeline.arms import ARMS

    add_run_options(parser)
    add_grid_options(parser)
    p = parser
    p.add_argument("--task", action="append", help="novel task (repeatable; default: the profile's)")
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


def _work(profile, out, args, progress, backend, command_line) -> None:
    from divmorph.pipeline.transfer import transfer

    arms = args.arms
    if args.no_scratch and arms is None:
        arms = [arm for arm in profile.transfer.arm_list() if arm != "scratch"]
    transfer(profile, out, args.task, progress, arms, args.seeds, backend, args.closest_by)


def run(args: argparse.Namespace) -> int:
    return run_on_folder(args, _work)
