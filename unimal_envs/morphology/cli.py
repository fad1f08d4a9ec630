"""``unimal-morphologies``: regenerate the shipped morphology sets and compare their statistics.

Examples::

    unimal-morphologies generate                      # rewrite the shipped train and novel sets
    unimal-morphologies generate --set train --out /tmp/sets
    unimal-morphologies generate --check              # verify the shipped files, write nothing
    unimal-morphologies stats --compare /path/to/unimals_100/train
    unimal-morphologies fetch                         # the official sets into $UNIMAL_DATA
    unimal-morphologies fetch --sets train --source /path/to/archive.tar.gz
    unimal-morphologies mutate unimals100-train --kind kinematic --out variations/train-kinematic

Also runnable as ``python -m unimal_envs.morphology``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from unimal_envs.morphology import official as O
from unimal_envs.morphology import sets as S
from unimal_envs.morphology import variations as V
from unimal_envs.morphology.loader import MorphologyError, is_set_name, morphology_files


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="unimal-morphologies", description="Generate the shipped UNIMAL morphology sets and show their statistics."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    gen = sub.add_parser("generate", help="regenerate the shipped sets from their fixed seeds")
    gen.add_argument("--out", type=Path, default=None, help="root directory (default: the package data directory)")
    gen.add_argument("--set", dest="which", choices=[*S.SETS, "all"], default="all", help="which set (default all)")
    gen.add_argument("--check", action="store_true", help="compare with the files under --out instead of writing")
    gen.add_argument("--quiet", action="store_true", help="no progress bar")
    gen.add_argument("--count", type=int, default=None, help="only the first COUNT robots of each set (quick checks)")
    gen.add_argument(
        "--stand-filter", type=float, default=None, metavar="RATIO",
        help="keep only robots whose torso stays above RATIO x standing height at zero torque (shipped sets: 0.5; "
             "0 = off); a value other than the shipped one needs --out",
    )  # fmt: skip
    gen.add_argument(
        "--jobs", type=int, default=min(os.cpu_count() or 1, 8),
        help="worker processes (default: CPU count, at most 8); the output does not depend on it",
    )  # fmt: skip
    stats = sub.add_parser("stats", help="statistics of the shipped sets, optionally beside other robot directories")
    stats.add_argument("--set", dest="which", choices=[*S.SETS, "all"], default="all", help="which set (default all)")
    stats.add_argument("--root", type=Path, default=None, help="read the sets from ROOT/<set> instead of the package")
    stats.add_argument(
        "--compare", action="append", default=[], metavar="SET_OR_DIR",
        help="also show a set (e.g. unimals100-train, once fetched) or a robot directory (xml/ inside); repeatable",
    )  # fmt: skip
    stats.add_argument("--markdown", type=Path, default=None, help="also write the table as markdown to this file")
    mutate = sub.add_parser("mutate", help="a reproducible set of kinematic or dynamic variations of any robot set (DERL's mutations)")
    mutate.add_argument("robots", help="a set name (unimals100-train, train, ...) or a robot directory")
    mutate.add_argument("--kind", choices=list(V.KINDS), required=True, help="kinematic (shape) or dynamic (densities, gears)")
    mutate.add_argument(
        "--out", type=Path, default=None,
        help="the variation set's folder (xml/, metadata/, VARIATIONS.json); default: its name "
             "<robots>-<kind>-s<seed> in the cache's variations/ folder ($UNIMAL_DATA)",
    )  # fmt: skip
    mutate.add_argument("--per-robot", type=int, default=1, help="variants of each robot (default 1)")
    mutate.add_argument("--seed", type=int, default=0, help="the set's seed (default 0); the same command gives the same files")
    mutate.add_argument("--quiet", action="store_true", help="no progress bar")
    fetch = sub.add_parser("fetch", help="download the official unimals_100 sets into the cache ($UNIMAL_DATA)")
    fetch.add_argument(
        "--source", default=None,
        help="URL, .tar.gz archive or directory (default: the authors' repository archive pinned to "
             f"commit {O.PINNED_COMMIT[:10]})",
    )  # fmt: skip
    fetch.add_argument("--sets", nargs="+", choices=list(O.SHORT_NAMES), default=list(O.SHORT_NAMES), help="which sets")
    fetch.add_argument("--cache", type=Path, default=None, help="cache folder (default $UNIMAL_DATA or ~/.cache/unimal_envs)")
    fetch.add_argument("--force", action="store_true", help="fetch again even if already cached")
    return parser


def _mutate(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    out = args.out if args.out is not None else V.default_folder(args.robots, args.kind, args.seed)
    files = V.make_variation_set(args.robots, args.kind, out, per_robot=args.per_robot, seed=args.seed, progress=not args.quiet)
    print(f'{len(files)} {args.kind} variants of {args.robots} in {out} ({time.perf_counter() - start:.0f} s; morphologies="{out}")')
    return 0


def _fetch(args: argparse.Namespace) -> int:
    folders = O.fetch(args.source, args.sets, cache=args.cache, force=args.force, progress=True)
    for name, folder in folders.items():
        spec = O.OFFICIAL_SETS[name]
        copies = f" ({len(spec.byte_copies)} byte copies of training robots left out)" if spec.byte_copies else ""
        print(f'{name}: {spec.robots} robots in {folder}{copies}  (morphologies="{name}")')
    return 0


def _generate(args: argparse.Namespace) -> int:
    root = args.out if args.out is not None else S.DATA_DIR
    status = 0
    made: dict[str, list] = {}
    for name in S.set_names(args.which):
        start = time.perf_counter()
        exclude = _exclusions(name, made, partial=args.count is not None)
        spec = S.SETS[name]
        if args.stand_filter is not None and args.stand_filter != spec.min_standing_ratio:
            if args.out is None:
                raise MorphologyError("--stand-filter changes the set; give --out to write it elsewhere than the shipped set")
            spec = dataclasses.replace(spec, min_standing_ratio=args.stand_filter)
        robots = S.generate_set(name, progress=not args.quiet, count=args.count, jobs=args.jobs, exclude=exclude, spec=spec)
        if args.count is None:
            made[name] = robots
        elapsed = time.perf_counter() - start
        if args.check:
            bad = S.compare_set(robots, root / name)
            shown = ", ".join(bad[:8]) + (" ..." if len(bad) > 8 else "")
            verdict = "identical" if not bad else f"{len(bad)} differ: {shown}"
            print(f"{name}: {len(robots)} robots generated in {elapsed:.1f} s; files under {root / name}: {verdict}")
            status = status or (1 if bad else 0)
        elif args.count is not None and args.out is None:
            raise MorphologyError("--count writes a partial set; give --out (or use --check) to keep the shipped set whole")
        else:
            S.write_set(robots, root / name, name)
            print(f"{name}: {len(robots)} robots generated in {elapsed:.1f} s -> {root / name}")
    return status


def _exclusions(name: str, made: dict[str, list], partial: bool) -> list[str] | None:
    """Body plans a set must avoid: from sets generated in this run, else (quick ``--count`` runs)
    from the shipped files, else ``None`` (generate_set then regenerates them in memory)."""
    others = S.SETS[name].disjoint_from
    if all(o in made for o in others):
        return [S.plan_signature(r.xml) for o in others for r in made[o]]
    if partial:
        return [S.plan_signature(p.read_text()) for o in others for p in morphology_files(S.DATA_DIR / o)]
    return None


def _print_table(rows: list[list[str]]) -> None:
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:  # plain aligned text without rich
        lines = [S.STATS_HEADER, *rows]
        widths = [max(len(r[i]) for r in lines) for i in range(len(S.STATS_HEADER))]
        for r in lines:
            print("  ".join(cell.ljust(w) for cell, w in zip(r, widths)).rstrip())
        return
    table = Table(title="UNIMAL morphology statistics")
    for column in S.STATS_HEADER:
        table.add_column(column, justify="right" if column in ("n", "min", "mean", "max") else "left")
    previous = None
    for row in rows:
        if previous is not None and row[0] != previous:
            table.add_section()
        table.add_row(*row)
        previous = row[0]
    Console(width=max(160, Console().width)).print(table)


def _stats(args: argparse.Namespace) -> int:
    sets = [S.set_stats(name, args.root) for name in S.set_names(args.which)]
    for other in args.compare:
        label = other if is_set_name(other) else f"{Path(other).name} ({Path(other).parent.name})"
        sets.append(S.collect_stats(label, morphology_files(other)))
    _print_table(S.stats_rows(sets))
    if args.markdown is not None:
        command = "python -m unimal_envs.morphology " + " ".join(sys.argv[1:] if argv_is_cli() else ["stats"])
        args.markdown.write_text(S.stats_markdown(sets, command))
        print(f"table written to {args.markdown}")
    return 0


def argv_is_cli() -> bool:
    """Whether this process was started as the morphology CLI (then sys.argv describes the command)."""
    return Path(sys.argv[0]).name in ("unimal-morphologies", "__main__.py", "cli.py")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``unimal-morphologies``.

    :param argv: command-line arguments (default ``sys.argv[1:]``).
    :returns: the exit status (1 when ``generate --check`` finds differences or input is bad).
    """
    args = _parser().parse_args(argv)
    try:
        if args.command == "fetch":
            return _fetch(args)
        if args.command == "mutate":
            return _mutate(args)
        return _generate(args) if args.command == "generate" else _stats(args)
    except MorphologyError as err:
        print(f"unimal-morphologies: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
