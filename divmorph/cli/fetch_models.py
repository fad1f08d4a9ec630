"""``divmorph fetch-models RUN --source ...``: a shipped run's models into the local cache, checked."""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="the shipped run (cpu100: the 100-robot run's teachers and students)")
    parser.add_argument(
        "--source", required=True, help="a checkout of the divmorph repository, a .tar.gz archive of it, or the URL of such an archive"
    )
    parser.add_argument("--cache", default=None, help="the cache folder (default $DIVMORPH_MODELS, else ~/.cache/divmorph/models)")
    parser.add_argument("--force", action="store_true", help="fetch again even if already cached")


def run(args: argparse.Namespace) -> int:
    from divmorph.shipped import ShippedModelsError, fetch_models

    try:
        folder = fetch_models(args.run, args.source, cache=args.cache, force=args.force)
    except ShippedModelsError as error:
        print(f"divmorph fetch-models: {error}", file=sys.stderr)
        return 2
    print(f'{args.run}: its models in {folder}; load_pretrained("results/{args.run}/teachers/FT") now finds them from any folder')
    return 0
