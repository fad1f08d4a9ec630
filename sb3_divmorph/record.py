"""Deprecated path of :mod:`divmorph.record`: the application lives in :mod:`divmorph` (CHANGELOG: when this path goes)."""

import importlib
import sys
import warnings

warnings.warn(
    "sb3_divmorph.record moved to divmorph.record in 0.2.0 (see CHANGELOG); the old path goes in 0.3.0", DeprecationWarning, stacklevel=2
)
# the module itself, so that its classes and errors are the same objects under both names
sys.modules[__name__] = importlib.import_module("divmorph.record")
