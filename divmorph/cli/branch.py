"""``divmorph branch``: a new run folder that reuses another run's finished stages."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

from divmorph.cli.run_folder import arms_list


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from divmorph.pipeline.branch import REUSABLE_STAGES

    parser.add_argument("--from", dest="source", required=True, help="the run folder whose finished stages are reused")
    parser.add_argument("--out", "--run", required=True, help="the new run folder (must not exist or be empty)")
    parser.add_argument(
        "--stages",
        type=arms_list,
        default=list(REUSABLE_STAGES),
        help=f"comma-separated stages to reuse (default: {','.join(REUSABLE_STAGES)})",
    )


def run(args: argparse.Namespace) -> int:
    from divmorph.pipeline.branch import branch
    from divmorph.pipeline.config import ConfigError

    command_line = "divmorph " + shlex.join(getattr(args, "argv", None) or sys.argv[1:])
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
