"""What every per-robot deployed actor shares (DivMorph's compact actor, ModuMorph's and
HyperDistill's folded actors): inputs, baked normalisation, size and FLOP accounting, ONNX export.

Every deployed actor has the same interface: ``forward(proprioceptive, hfield, goal, object)`` on
the env's *raw* arrays -> (B, 24) action means, with the ``VecNormalize`` statistics baked in, so
:func:`~sb3_divmorph.deploy.compact.export_torchscript` and :func:`export_onnx` serve all of them, and
:class:`sb3_divmorph.deploy.onnx_actor.OnnxActor` runs any ONNX file without torch.
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

from sb3_divmorph.nn.extractors import EXTEROCEPTION_KEYS, OBS_PADDING_MASK, PROPRIOCEPTIVE

#: positional inputs of every deployed actor, in ``forward`` order
ACTOR_INPUTS = (PROPRIOCEPTIVE, *EXTEROCEPTION_KEYS)


def actor_inputs(observation: Mapping[str, np.ndarray], batch: bool = False) -> tuple[th.Tensor, ...]:
    """A deployed actor's positional inputs from an observation dict (adds a batch axis unless ``batch``)."""
    values = (np.asarray(observation[k], dtype=np.float32) for k in ACTOR_INPUTS)
    return tuple(th.as_tensor(v if batch else v[None]) for v in values)


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
                # float64 like VecNormalize's own numpy arithmetic: a nearly constant feature has a huge
                # inverse std, and float32 rounding of (x - mean) would be amplified by it (trained
                # students differed by 4e-5 from the unpruned student with float32 statistics)
                mean = th.as_tensor(rms.mean, dtype=th.float64)
                inv_std = th.as_tensor(1.0 / np.sqrt(rms.var + normalizer.epsilon), dtype=th.float64)
                if key == PROPRIOCEPTIVE:
                    mean, inv_std = mean[real_tokens], inv_std[real_tokens]
                self.register_buffer(f"{key}_mean", mean)
                self.register_buffer(f"{key}_inv_std", inv_std)
                self.normalized_keys.append(key)
        self.clip_obs = float(getattr(normalizer, "clip_obs", math.inf)) if normalizer is not None else math.inf

    def _normalize(self, key: str, x: th.Tensor) -> th.Tensor:
        if key not in self.normalized_keys:
            return x
        x = (x.double() - getattr(self, f"{key}_mean")) * getattr(self, f"{key}_inv_std")
        return (x.clamp(-self.clip_obs, self.clip_obs) if math.isfinite(self.clip_obs) else x).float()

    def _fuse_and_decode(self, x: th.Tensor, hfield: th.Tensor, goal: th.Tensor, object: th.Tensor) -> th.Tensor:  # noqa: A002
        """The Transformer actors' common tail: (B, real tokens, D) token features -> late-fused
        exteroception -> per-token decoder -> (B, 24) action means, 0 on padded slots.

        Needs ``used_extero``, ``exteroception``, ``decoder``, ``decoder_activations``,
        ``action_scale``, ``real_tokens``, ``n_tokens`` and ``slots`` (set by ``from_policy``).
        """
        inputs = {"hfield": hfield, "goal": goal, "object": object}
        if self.used_extero:
            extero = th.cat([self.exteroception[k](self._normalize(k, inputs[k].flatten(1))) for k in self.used_extero], dim=-1)
            x = th.cat([x, extero[:, None, :].expand(-1, x.shape[1], -1)], dim=-1)
        for layer, activation in zip(self.decoder, self.decoder_activations):
            x = activation(layer(x))
        out = x.new_zeros(x.shape[0], self.n_tokens, self.slots)
        return out.index_copy(1, self.real_tokens, x * self.action_scale).flatten(1)

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


def export_onnx(actor: nn.Module, example: Mapping[str, np.ndarray], path: str | Path, metadata: Mapping[str, Any]) -> Path:
    """Write a deployed actor as ONNX to ``path`` atomically, for ``onnxruntime`` + ``numpy`` alone.

    The graph keeps only the inputs the actor reads (e.g. FT's actor has no ``hfield`` input), with
    a free batch axis (torch's TorchScript-based exporter: the ``torch.export`` one needs
    ``onnxscript``). ``metadata`` (robot, task, ...) is stored in the model's ``metadata_props``,
    with the inputs' names and shapes and the robot's ``obs_padding_mask``, which
    :class:`sb3_divmorph.deploy.onnx_actor.OnnxActor` checks observations against.

    :param actor: a deployed actor (``CompactActor``, ``ModuMorphActor``, ``HyperDistillMLP``).
    :param example: one raw observation (unbatched) of the robot and task.
    :param path: output ``.onnx`` file.
    :param metadata: string-able key/values stored in the file.
    """
    import onnx

    path = Path(path)
    names = list(ACTOR_INPUTS)
    buffer = io.BytesIO()
    with th.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript-based exporter's deprecation notice
        th.onnx.export(
            actor.eval(),
            actor_inputs(example),
            buffer,
            input_names=names,
            output_names=["actions"],
            dynamic_axes={name: {0: "batch"} for name in [*names, "actions"]},
            dynamo=False,
            opset_version=17,
        )
    model = onnx.load_from_string(buffer.getvalue())
    kept = [i.name for i in model.graph.input]
    props = {
        **{str(k): v if isinstance(v, str) else json.dumps(v) for k, v in metadata.items()},
        "inputs": json.dumps({k: list(np.asarray(example[k]).shape) for k in kept}),
    }
    if OBS_PADDING_MASK in example:
        props[OBS_PADDING_MASK] = json.dumps(np.asarray(example[OBS_PADDING_MASK], dtype=np.float32).reshape(-1).tolist())
    onnx.helper.set_model_props(model, props)
    onnx.checker.check_model(model)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(model.SerializeToString())
    tmp.replace(path)
    return path
