"""``divmorph export``: prune + merge the student into a compact actor (ONNX and/or TorchScript)."""

from __future__ import annotations

import argparse
from pathlib import Path

from divmorph.cli.run_folder import add_run_options, run_on_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_options(parser)
    p = parser
    p.add_argument("--morphology", action="append", help="robot name in the train/novel sets, or an MJCF path")
    p.add_argument("--task", action="append", help="task (default: the profile's)")
    p.add_argument(
        "--format",
        choices=("onnx", "torchscript", "all"),
        default="all",
        help="onnx (runs with onnxruntime + numpy), torchscript (torch alone), or all (default)",
    )
    p.add_argument(
        "--student",
        action="append",
        help="distilled DivMorph student to deploy (repeatable; default: divmorph and every finished deploy-* student)",
    )


def robot_path(name: str, profile=None) -> Path:
    """A robot by MJCF path, or by name among the profile's robots (every split), else the shipped sets."""
    from divmorph.pipeline.robots import profile_robots, profile_splits
    from unimal_envs.morphology.loader import morphology_files

    path = Path(name)
    if path.suffix == ".xml":
        if not path.is_file():
            raise FileNotFoundError(f"MJCF file {path} does not exist")
        return path
    candidates = [(split, lambda split=split: profile_robots(profile, split)) for split in profile_splits(profile)] if profile else []
    candidates += [(split, lambda split=split: morphology_files(split)) for split in ("train", "novel")]
    for _, files in candidates:
        for file in files():
            if file.stem == name:
                return file
    where = "the run's robots or " if profile else ""
    raise ValueError(f"unknown morphology {name!r}: give a robot of {where}the train/novel sets (e.g. train-000) or an MJCF path")


def _work(profile, out, args, progress, backend, command_line) -> None:
    from divmorph.pipeline.export import export_all

    robots = [robot_path(m, profile) for m in args.morphology] if args.morphology else None
    formats = ("onnx", "torchscript") if args.format == "all" else (args.format,)
    for r in export_all(profile, out, args.task, robots, formats, args.student):
        print(
            f"{r['student']}: {r['robot']} x {r['task']}: {r['compact_weights']:,} weights "
            f"({r['reduction_vs_metamorph']:.1f}x smaller than MetaMorph's actor through the same folding), "
            f"max |diff| {r['max_abs_diff']:.1e}, "
            f"latency {r['latency_compact_ms']:.3f} ms vs {r['latency_student_ms']:.3f} ms, "
            f"return {r['compact_return']:.1f} (student {r['student_return']:.1f})"
        )


def run(args: argparse.Namespace) -> int:
    return run_on_folder(args, _work, reads_a_run=True, trains=False)
