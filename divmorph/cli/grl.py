"""``divmorph grl``: the GRL baseline's evolution; its best learngene for the ``grl`` arm."""

from __future__ import annotations

import argparse
from pathlib import Path

from divmorph.cli.run_folder import add_grid_options, add_run_options, run_on_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_options(parser)
    add_grid_options(parser)


def _work(profile, out, args, progress, backend, command_line) -> None:
    from divmorph.pipeline.grl import evolve

    learngene = evolve(profile, out, backend, progress)
    print(
        f"learngene: {'+'.join(learngene['units'])} (agent {learngene['agent']} of generation {learngene['generation']}, "
        f"{learngene['task']}) -> {Path(out) / 'grl' / 'learngene.json'}"
    )


def run(args: argparse.Namespace) -> int:
    return run_on_folder(args, _work)
