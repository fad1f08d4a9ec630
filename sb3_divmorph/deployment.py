"""Shared pieces of the per-robot deployed actors of the baselines (ModuMorph, HyperDistill).

Every deployed actor has the interface of :class:`~sb3_divmorph.compact.CompactActor`:
``forward(proprioceptive, hfield, goal, object)`` on the env's *raw* arrays -> (B, 24) action means,
with the ``VecNormalize`` statistics baked in, so :func:`~sb3_divmorph.compact.export_torchscript`
and :func:`export_onnx` serve all of them.

:func:`export_onnx` is a small self-contained ONNX export (torch's TorchScript-based exporter;
the newer ``torch.export`` one needs ``onnxscript``). It is one function so that a common exporter
can replace it.
"""

from __future__ import annotations

import io
import json
import math
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from sb3_divmorph.extractors import PROPRIOCEPTIVE

#: positional inputs of every deployed actor, in ``forward`` order
ACTOR_INPUT_NAMES = ("proprioceptive", "hfield", "goal", "object")


class DeployedActor(nn.Module):
    """Base of the folded per-robot actors: baked observation normalisation and size accounting."""

    normalized_keys: list[str]
    clip_obs: float

    def bake_normalization(self, normalizer: Any | None, real_tokens: th.Tensor, keys: list[str]) -> None:
        """Store ``VecNormalize`` mean / inverse std of ``proprioceptive`` (real rows) and ``keys`` as buffers.

        :param normalizer: the policy's ``VecNormalize``, or ``None`` (raw observations).
        :param real_tokens: indices of the robot's real tokens.
        :param keys: the exteroception keys that stay inputs.
        """
        self.normalized_keys = []
        norm_keys = set(getattr(normalizer, "norm_obs_keys", None) or []) if normalizer is not None else set()
        for key in (PROPRIOCEPTIVE, *keys):
            if key in norm_keys:
                rms = normalizer.obs_rms[key]
                mean = th.as_tensor(rms.mean, dtype=th.float32)
                inv_std = th.as_tensor(1.0 / np.sqrt(rms.var + normalizer.epsilon), dtype=th.float32)
                if key == PROPRIOCEPTIVE:
                    mean, inv_std = mean[real_tokens], inv_std[real_tokens]
                self.register_buffer(f"{key}_mean", mean)
                self.register_buffer(f"{key}_inv_std", inv_std)
                self.normalized_keys.append(key)
        self.clip_obs = float(getattr(normalizer, "clip_obs", math.inf)) if normalizer is not None else math.inf

    def _normalize(self, key: str, x: th.Tensor) -> th.Tensor:
        if key not in self.normalized_keys:
            return x
        x = (x - getattr(self, f"{key}_mean")) * getattr(self, f"{key}_inv_std")
        return x.clamp(-self.clip_obs, self.clip_obs) if math.isfinite(self.clip_obs) else x

    def stored_numbers(self) -> dict[str, int]:
        """Numbers stored: ``weights`` (parameters incl. folded constants) and ``normalization``."""
        normalization = sum(b.numel() for n, b in self.named_buffers() if n.endswith(("_mean", "_inv_std")))
        return {"weights": sum(p.numel() for p in self.parameters()), "normalization": normalization}


def matmul_flops(fn, inputs: tuple) -> int:
    """FLOPs of one call, counted by ``torch.utils.flop_counter`` (2 per multiply-add of matmuls,
    linear layers and attention; element-wise ops, norms and softmax are not counted)."""
    with th.no_grad(), FlopCounterMode(display=False) as counter:
        fn(*inputs)
    return int(counter.get_total_flops())


def export_onnx(actor: nn.Module, example: tuple[th.Tensor, ...], path: str | Path, metadata: Mapping[str, Any] | None = None) -> Path:
    """Write ``actor`` as ONNX (dynamic batch axis; inputs ``proprioceptive, hfield, goal, object``,
    output ``actions``), atomically; ``metadata`` goes into the model's ``metadata_props``.

    The file runs with ``onnxruntime`` alone (no torch). Inputs the task does not use (e.g. ``hfield``
    on FT) are not in the graph: feed the names ``session.get_inputs()`` lists.

    :param actor: a deployed actor (e.g. :class:`~sb3_divmorph.hyperdistill.HyperDistillMLP`).
    :param example: one batch of its positional inputs (``compact.actor_inputs``).
    :param path: output ``.onnx`` file.
    :param metadata: string-able key/values stored in the file.
    """
    import onnx  # optional dependency (extra "deploy")

    path = Path(path)
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript-based exporter
        th.onnx.export(
            actor.eval(),
            tuple(example),
            buffer,
            dynamo=False,
            input_names=list(ACTOR_INPUT_NAMES),
            output_names=["actions"],
            dynamic_axes={name: {0: "batch"} for name in (*ACTOR_INPUT_NAMES, "actions")},
            opset_version=17,
        )
    model = onnx.load_from_string(buffer.getvalue())
    for key, value in (metadata or {}).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = str(key), value if isinstance(value, str) else json.dumps(value)
    onnx.checker.check_model(model)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(model.SerializeToString())
    tmp.replace(path)
    return path
