"""``divmorph evaluate``: a run's per-robot returns on train and novel robots, or one saved model's."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from divmorph.cli.run_folder import add_run_options, run_on_folder


def part(text: str) -> tuple[int, int]:
    """``"k/n"`` (``--part``) as ``(k, n)`` with 1 <= k <= n."""
    try:
        k, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a part is K/N, e.g. 1/2, got {text!r}") from None
    if not 1 <= k <= n:
        raise argparse.ArgumentTypeError(f"a part K/N needs 1 <= K <= N, got {text!r}")
    return k, n


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_options(parser)
    p = parser
    p.add_argument(
        "source",
        nargs="?",
        default=None,
        help="instead of a run: one model folder (a pipeline stage, an rl-zoo run folder or a .zip), evaluated on "
        "the robots and env settings it was trained with (or --robots), its returns printed and written to --into",
    )
    p.add_argument("--robots", default=None, help="with a model folder: a robot set, folder or name (default: its own robots)")
    p.add_argument(
        "--model",
        action="append",
        dest="models",
        help="only this model label (repeatable): teacher, teacher-untrained, student, student-<name>, hyperdistill, transfer-<arm>",
    )
    p.add_argument("--task", action="append", dest="eval_tasks", help="only this task (repeatable)")
    p.add_argument(
        "--split",
        action="append",
        dest="splits",
        choices=("train", "novel", "ood"),
        help="only these robots (repeatable; ood: the profile's out-of-distribution set)",
    )
    p.add_argument("--episodes", type=int, default=None, help="episodes per robot (default: the profile's evaluate.episodes)")
    p.add_argument(
        "--into",
        type=Path,
        default=None,
        help="folder for the selection's returns.csv (default: evaluations/<run>-<time>/ here); a selection never writes into the run's evaluate/",
    )
    p.add_argument(
        "--part",
        type=part,
        default=None,
        metavar="K/N",
        help="evaluate the k-th of n shares of the run's evaluation (n processes, one per core); a plain evaluate afterwards merges them and finishes",
    )


def evaluate_model_folder(args: argparse.Namespace) -> int:
    """``divmorph evaluate FOLDER``: any saved model, on its own robots and settings (``load_pretrained``)."""
    import csv

    import torch as th

    from divmorph.pretrained import PretrainedError, load_pretrained

    th.set_num_threads(1)
    if args.episodes is not None and args.episodes < 1:
        print(f"divmorph evaluate: --episodes must be at least 1, got {args.episodes}", file=sys.stderr)
        return 2
    tasks = args.eval_tasks or [None]
    try:
        model = load_pretrained(args.source)
        rows = []
        for task in tasks:
            found = model.evaluate(args.robots, task=task, episodes=args.episodes or 1, seed=args.seed or 0)
            rows += [{"model": str(args.source), "task": task or (model.env_id or "").split("-")[1], **row} for row in found]
    except (PretrainedError, ValueError, FileNotFoundError) as error:
        print(f"divmorph evaluate: {error}", file=sys.stderr)
        return 2
    for row in sorted(rows, key=lambda r: (r["task"], r["robot"], r["episode"])):
        print(f"{row['task']} {row['robot']} episode {row['episode']}: return {row['return']:.1f} over {row['length']} steps")
    means = {task: [r["return"] for r in rows if r["task"] == task] for task in dict.fromkeys(r["task"] for r in rows)}
    for task, values in means.items():
        print(f"{task}: mean return {sum(values) / len(values):.1f} over {len(values)} episodes")
    if args.into is not None:
        args.into.mkdir(parents=True, exist_ok=True)
        with open(args.into / "returns.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=["model", "task", "robot", "episode", "return", "length"])
            writer.writeheader()
            writer.writerows(rows)
        print(f"-> {args.into / 'returns.csv'}")
    return 0


def _work(profile, out, args, progress, backend, command_line) -> None:
    from divmorph.pipeline.evaluate import evaluate

    folder = evaluate(profile, out, progress, args.models, args.eval_tasks, args.splits, args.episodes, args.into, args.part)
    print(f"returns -> {folder / 'returns.csv'}")


def run(args: argparse.Namespace) -> int:
    if args.source is not None:
        return evaluate_model_folder(args)
    # an evaluation of a selection only reads the run: its records stay as they are
    selection = any(getattr(args, k) is not None for k in ("models", "eval_tasks", "splits", "episodes", "into"))
    return run_on_folder(args, _work, reads_a_run=True, records=not selection, trains=False)
