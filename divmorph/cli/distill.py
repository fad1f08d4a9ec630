"""``divmorph distill``: DAgger distillation of the teachers into the DivMorph student (and the arms' students)."""

from __future__ import annotations

import argparse

from divmorph.cli.run_folder import add_grid_options, add_run_options, arms_list, run_on_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_options(parser)
    add_grid_options(parser)
    parser.add_argument("--arms", type=arms_list, default=None, help="also distil the students these arms start from (comma-separated)")
    parser.add_argument(
        "--students",
        type=arms_list,
        default=None,
        help="distil exactly these students (comma-separated; see `divmorph.pipeline.students.STUDENTS`), e.g. deploy-g1k1",
    )


def _work(profile, out, args, progress, backend, command_line) -> None:
    from divmorph.pipeline.arms import students_for
    from divmorph.pipeline.config import ConfigError, check_arms
    from divmorph.pipeline.distill import distill

    if args.arms is not None and args.students is not None:
        raise ConfigError("give --arms or --students, not both")
    if args.arms is not None:
        check_arms(args.arms, "--arms")
    students = args.students if args.arms is None else ["divmorph", *students_for(args.arms)]
    distill(profile, out, progress, students, backend)


def run(args: argparse.Namespace) -> int:
    return run_on_folder(args, _work)
