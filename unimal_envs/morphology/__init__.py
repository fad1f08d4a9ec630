"""UNIMAL morphologies: loading MJCF robots and generating new ones."""

from unimal_envs.morphology.generator import generate_unimal, mutate
from unimal_envs.morphology.loader import (
    Morphology,
    MorphologyError,
    load_morphologies,
    load_morphology,
    morphology_files,
    parse_morphology,
)

__all__ = [
    "Morphology",
    "MorphologyError",
    "generate_unimal",
    "load_morphologies",
    "load_morphology",
    "morphology_files",
    "mutate",
    "parse_morphology",
]
