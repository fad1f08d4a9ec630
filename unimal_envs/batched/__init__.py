"""UNIMAL on MuJoCo Warp: thousands of worlds per call, the same tasks and observations.

``make_batched_env(task, morphologies, worlds_per_robot, device)`` simulates every robot of a set
in ``worlds_per_robot`` worlds of one MuJoCo Warp model per robot, computes observations, rewards,
terminations and resets on the device, and exposes the batch as a Stable-Baselines3 ``VecEnv``
(``PPO(DivMorphPolicy, env)`` works unchanged) and as torch tensors
(:meth:`BatchedUnimalEnv.step_tensors`). It needs the ``mujoco-warp`` extra::

    pip install "divmorph[warp]"

>>> from unimal_envs.batched import make_batched_env
>>> env = make_batched_env("FT", morphologies="train", worlds_per_robot=64, device="cuda")
"""

from __future__ import annotations

from typing import Any

try:
    import warp as _wp

    # No start-up banner and no line per compiled kernel (hundreds on first use); warnings stay.
    # (log_level does both: the config.quiet this also set is gone from Warp, so setting it did nothing.)
    _wp.config.log_level = max(_wp.config.log_level, _wp.LOG_WARNING)
    import mujoco_warp as _mjw  # noqa: F401
except ImportError as _error:  # pragma: no cover - exercised by a test that hides the package
    _MISSING: ImportError | None = _error
else:
    _MISSING = None


def require_warp() -> None:
    """Raise a clear error when MuJoCo Warp is not installed."""
    if _MISSING is not None:
        raise ImportError(
            "the batched backend needs MuJoCo Warp, which is not installed: "
            'pip install "divmorph[warp]" (or pip install mujoco-warp==4.0.0)'
            f" [{_MISSING}]"
        ) from _MISSING


def make_batched_env(*args: Any, **kwargs: Any):
    """Build a :class:`BatchedUnimalEnv`; see :func:`unimal_envs.batched.env.make_batched_env`."""
    require_warp()
    from unimal_envs.batched.env import make_batched_env as make

    return make(*args, **kwargs)


def __getattr__(name: str):
    if name in ("BatchedUnimalEnv", "estimate_memory"):
        require_warp()
        from unimal_envs.batched import env

        return getattr(env, name)
    raise AttributeError(name)


__all__ = ["BatchedUnimalEnv", "make_batched_env", "require_warp"]
