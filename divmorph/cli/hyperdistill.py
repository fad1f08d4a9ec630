"""``divmorph hyperdistill``: the HyperDistill baseline (hypernetwork student, per-robot MLPs)."""

from __future__ import annotations

import argparse
from pathlib import Path

from divmorph.cli.run_folder import add_run_options, run_on_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_options(parser)


def _work(profile, out, args, progress, backend, command_line) -> None:
    from divmorph.pipeline.hyperdistill import hyperdistill

    for r in hyperdistill(profile, out, progress):
        print(
            f"{r['robot']} x {r['task']}: MLP of {r['mlp_weights']:,} weights, max |diff| {r['max_abs_diff']:.1e}, "
            f"latency {r['latency_mlp_ms']:.3f} ms -> {Path(out) / 'hyperdistill' / 'export'}"
        )


def run(args: argparse.Namespace) -> int:
    return run_on_folder(args, _work)
