"""Deprecated path of :mod:`divmorph.pipeline`: the application lives in :mod:`divmorph` (CHANGELOG: when this path goes).

Importing ``sb3_divmorph.pipeline`` or any of its modules warns once and gives the module of
``divmorph.pipeline`` under the old name (the same objects: ``except ConfigError`` keeps working).
"""

import importlib
import pkgutil
import sys
import warnings

warnings.warn(
    "sb3_divmorph.pipeline moved to divmorph.pipeline in 0.2.0 (see CHANGELOG); the old path goes in 0.3.0",
    DeprecationWarning,
    stacklevel=2,
)
_moved = importlib.import_module("divmorph.pipeline")
for _info in pkgutil.iter_modules(_moved.__path__):
    sys.modules[f"{__name__}.{_info.name}"] = importlib.import_module(f"divmorph.pipeline.{_info.name}")
sys.modules[__name__] = _moved
