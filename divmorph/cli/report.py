"""``divmorph report``: the run's plots, the paper's figures and a markdown summary."""

from __future__ import annotations

import argparse

from divmorph.cli.run_folder import add_run_options, run_on_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_options(parser)


def _work(profile, out, args, progress, backend, command_line) -> None:
    from divmorph.pipeline.report import report

    print(report(profile, out, command_line))


def run(args: argparse.Namespace) -> int:
    return run_on_folder(args, _work, reads_a_run=True, trains=False)
