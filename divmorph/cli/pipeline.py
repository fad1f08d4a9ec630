"""``divmorph pipeline``: every stage in order, finished ones skipped."""

from __future__ import annotations

import argparse

from divmorph.cli.run_folder import add_grid_options, add_run_options, run_on_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_options(parser)
    add_grid_options(parser)


def _work(profile, out, args, progress, backend, command_line) -> None:
    from divmorph.pipeline import run_pipeline

    print(run_pipeline(profile, out, progress, command_line, backend))


def run(args: argparse.Namespace) -> int:
    return run_on_folder(args, _work)
