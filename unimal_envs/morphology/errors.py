"""The one error of the morphology package, below every module that raises it."""

from __future__ import annotations


class MorphologyError(ValueError):
    """A file or argument that does not describe a usable UNIMAL robot."""
