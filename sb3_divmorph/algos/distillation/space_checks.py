"""Refusing a saved model or normaliser that was trained on another observation or action space."""

from __future__ import annotations

from gymnasium import spaces


class SpaceMismatchError(ValueError):
    """A saved model or normaliser does not fit the observation/action space it is used with."""


def check_spaces(what: str, saved: spaces.Space, expected: spaces.Space, kind: str = "observation") -> None:
    """Raise :class:`SpaceMismatchError` naming ``what`` and the differing keys if the spaces differ."""
    if saved == expected:
        return
    detail = ""
    if isinstance(saved, spaces.Dict) and isinstance(expected, spaces.Dict):
        differing = sorted(
            key
            for key in set(saved.spaces) | set(expected.spaces)
            if key not in saved.spaces or key not in expected.spaces or saved[key] != expected[key]
        )
        shapes = {k: (getattr(saved.spaces.get(k), "shape", None), getattr(expected.spaces.get(k), "shape", None)) for k in differing}
        detail = f"; differing keys (saved shape, env shape): {shapes}"
    else:
        detail = f"; saved {saved}, env {expected}"
    raise SpaceMismatchError(f"{what} was trained on a different {kind} space than this environment's{detail}")
