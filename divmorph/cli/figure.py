"""``divmorph figure NAME``: one of the paper's figures (PNG + CSV in the run's report/figures/)."""

from __future__ import annotations

import argparse
import sys

from divmorph.cli.run_folder import add_run_options, run_on_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_options(parser)
    parser.add_argument("name", help="transfer-train, transfer-novel, deployment, pareto, ablation or gates")


def _work(profile, out, args, progress, backend, command_line) -> None:
    from divmorph.pipeline.figures import make_figure

    path = make_figure(profile, out, args.name)
    if path is None:
        raise FileNotFoundError(f"no data for figure {args.name!r} in {out} yet (run the stages it plots first)")
    print(f"{args.name} -> {path} (numbers: {path.with_suffix('.csv')})")


def run(args: argparse.Namespace) -> int:
    from divmorph.pipeline.figures import FIGURES

    if args.name not in FIGURES:  # a typo in the name, before anything about the run
        print(f"divmorph figure: unknown figure {args.name!r}; figures: {list(FIGURES)}", file=sys.stderr)
        return 2
    return run_on_folder(args, _work, reads_a_run=True, trains=False)
