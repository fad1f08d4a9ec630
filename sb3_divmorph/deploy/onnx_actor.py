"""Run an exported actor (``actor.onnx``) with ``onnxruntime`` and ``numpy`` only.

This module imports nothing else, on purpose: copy it next to a robot's controller, where neither
torch nor this project is installed::

    actor = OnnxActor("runs/demo/export/train-000-FT/actor.onnx")
    print(actor.metadata["robot"], actor.metadata["task"], actor.input_shapes)
    action = np.clip(actor(observation), -1, 1)   # observation: the env's dict, one step or a batch

The file records the robot and task it was made for, its inputs' names and shapes, and the robot's
``obs_padding_mask``; an observation with a wrong shape, a missing input or another robot's
padding is refused with an error that says which.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import onnxruntime


class ObservationMismatchError(ValueError):
    """An observation does not fit the exported actor (shape, missing key, other robot)."""


class OnnxActor:
    """A deterministic actor exported by ``divmorph export --format onnx``.

    :param path: the ``.onnx`` file.
    :param threads: intra-op threads of the ONNX Runtime session (1 = lowest batch-1 latency).
    """

    def __init__(self, path: str | Path, threads: int = 1):
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = threads
        self.session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        props = dict(self.session.get_modelmeta().custom_metadata_map)
        self.input_shapes: dict[str, tuple[int, ...]] = {k: tuple(v) for k, v in json.loads(props.pop("inputs")).items()}
        padding = props.pop("obs_padding_mask", None)
        self.obs_padding_mask = None if padding is None else np.asarray(json.loads(padding), dtype=np.float32)
        #: what the exporter recorded (robot, task, source model, ...)
        self.metadata: dict[str, str] = props

    def __call__(self, observation: Mapping[str, np.ndarray]) -> np.ndarray:
        """Action means for one observation (``(24,)``) or a batch (``(B, 24)``); clip to [-1, 1]
        before ``env.step``.

        :param observation: the env's observation dict (extra keys are ignored).
        :raises ObservationMismatchError: a missing input, a wrong shape, or another robot.
        """
        feed, batched = {}, None
        for name, shape in self.input_shapes.items():
            if name not in observation:
                raise ObservationMismatchError(f"observation has no {name!r}; this actor needs {sorted(self.input_shapes)}")
            value = np.asarray(observation[name], dtype=np.float32)
            is_batch = value.shape[1:] == shape
            if not is_batch and value.shape != shape:
                raise ObservationMismatchError(
                    f"{name!r} has shape {value.shape}; this actor takes {shape} or a batch (B, {', '.join(map(str, shape))})"
                )
            if batched is not None and is_batch != batched:
                raise ObservationMismatchError("mixed batched and unbatched inputs")
            batched = is_batch
            feed[name] = value if is_batch else value[None]
        if self.obs_padding_mask is not None and "obs_padding_mask" in observation:
            padding = np.asarray(observation["obs_padding_mask"], dtype=np.float32).reshape(-1, len(self.obs_padding_mask))
            if not np.all(padding == self.obs_padding_mask):
                raise ObservationMismatchError(
                    f"observation of a robot with {int((padding[0] < 0.5).sum())} limbs (tokens); this actor was exported for "
                    f"{self.metadata.get('robot', 'another robot')} with {int((self.obs_padding_mask < 0.5).sum())}"
                )
        actions = self.session.run(["actions"], feed)[0]
        return actions if batched else actions[0]
