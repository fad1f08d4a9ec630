"""``divmorph profiles``: the profile names (or one profile, validated) and the file they are read from."""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", help="print this profile's settings")
    parser.add_argument("--profiles", default="zoo_configs/divmorph.yml", help="profiles file (default: the shipped one)")


def run(args: argparse.Namespace) -> int:
    import dataclasses

    import yaml

    from divmorph.pipeline.config import ConfigError, load_profile, load_profiles, resolve_path

    try:
        names = sorted(load_profiles(args.profiles))
        if args.profile is not None:
            settings = dataclasses.asdict(load_profile(args.profile, args.profiles))
    except ConfigError as error:
        print(f"divmorph: {error}", file=sys.stderr)
        return 2
    print(f"# {resolve_path(args.profiles).resolve()}")
    print(yaml.safe_dump({args.profile: settings}, sort_keys=False) if args.profile is not None else "\n".join(names))
    return 0
