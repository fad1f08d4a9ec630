"""Deployment: a DivMorph student pruned and merged into a compact actor for one robot and task.

For a fixed morphology and task every gate is a constant, so (DivMorph's deployment pruning):

* tailors with a zero gate contribute nothing and are dropped; the remaining units of each layer
  are merged into one low-rank product ``A B^T`` (``A = U_sel diag(s_sel * g)``, ``B = V_sel``), or
  into a dense matrix where that is smaller;
* the router (morphology encoder, gates), the text embedding and the critic are not needed;
* inputs that are constant for this robot and task are folded into biases: the ``context`` rows,
  the position embedding, padded tokens (the actor runs on the robot's real tokens only), and the
  exteroception encoders of observations the task does not provide;
* the observation normalisation (``VecNormalize`` statistics) is baked in.

:class:`CompactActor` is plain PyTorch (no SB3, no ``sb3_divmorph`` needed to run it) and is
written as TorchScript by :func:`export_torchscript`, loadable with ``torch.jit.load`` alone.
"""

from __future__ import annotations

import copy
import io
import json
import statistics
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from torch import nn
from torch.nn import functional as F

from sb3_divmorph.deploy.deployment import ACTOR_INPUTS, DeployedActor, actor_inputs, export_onnx
from sb3_divmorph.nn.extractors import ACT_PADDING_MASK, CONTEXT, OBS_PADDING_MASK, PROPRIOCEPTIVE
from sb3_divmorph.nn.layers import FactorizedLinear

__all__ = ["ACTOR_INPUTS", "CompactActor", "actor_inputs", "export_onnx", "export_torchscript", "size_comparison"]


class LowRankLinear(nn.Module):
    """``y = (x B) A^T + b``: the merged selected units of a factorized layer.

    :param A: (out, k) left factors times the gated singular values.
    :param B: (in, k) right factors.
    :param bias: (out,) or ``None``.
    """

    def __init__(self, A: th.Tensor, B: th.Tensor, bias: th.Tensor | None):
        super().__init__()
        self.A = nn.Parameter(A.detach().clone(), requires_grad=False)
        self.B = nn.Parameter(B.detach().clone(), requires_grad=False)
        self.bias = None if bias is None else nn.Parameter(bias.detach().clone(), requires_grad=False)

    def forward(self, x: th.Tensor) -> th.Tensor:
        return F.linear(x @ self.B, self.A, self.bias)


def _frozen_linear(weight: th.Tensor, bias: th.Tensor | None) -> nn.Linear:
    layer = nn.Linear(weight.shape[1], weight.shape[0], bias=bias is not None)
    layer.weight = nn.Parameter(weight.detach().clone(), requires_grad=False)
    if bias is not None:
        layer.bias = nn.Parameter(bias.detach().clone(), requires_grad=False)
    return layer


def merged_layer(
    layer: nn.Module, tailor_gates: th.Tensor | None, input_rows: th.Tensor | None = None, constant_input: th.Tensor | None = None
) -> nn.Module:
    """The pruned, merged equivalent of one (dense or factorized) layer for fixed gates.

    :param layer: a :class:`DenseLinear`/``nn.Linear`` or :class:`FactorizedLinear`.
    :param tailor_gates: (N_m + N_t,) gates of the robot and task (``None`` for ungated layers).
    :param input_rows: keep only these input features (the others are ``constant_input``).
    :param constant_input: values of the dropped input features; their contribution joins the bias.
    :return: a :class:`LowRankLinear` or an ``nn.Linear``, whichever stores fewer numbers.
    """
    with th.no_grad():
        if isinstance(layer, FactorizedLinear):
            U, s, V = layer.selected_units(tailor_gates if layer.n_tailors else None)
            A, B = U * s, V
        else:
            A, B = layer.weight, None
        bias = None if layer.bias is None else layer.bias.clone()
        if input_rows is not None:
            everything = th.arange((B if B is not None else A.T).shape[0])
            dropped = everything[~th.isin(everything, input_rows)]
            if len(dropped):
                const = constant_input.to(A.dtype)
                extra = A @ (B[dropped].T @ const) if B is not None else A[:, dropped] @ const
                bias = extra if bias is None else bias + extra
            if B is not None:
                B = B[input_rows]
            else:
                A = A[:, input_rows]
        if B is None:
            return _frozen_linear(A, bias)
        out_dim, rank = A.shape
        in_dim = B.shape[0]
        if rank * (in_dim + out_dim) < in_dim * out_dim:
            return LowRankLinear(A, B, bias)
        return _frozen_linear(A @ B.T, bias)


def merged_encoder(encoder: nn.Sequential, tailor_gates: th.Tensor | None) -> nn.Sequential:
    """An exteroception encoder (layers and ReLUs) with every layer pruned and merged."""
    return nn.Sequential(*(m if isinstance(m, nn.ReLU) else merged_layer(m, tailor_gates) for m in encoder))


class CompactBlock(nn.Module):
    """A pre-LN Transformer layer over the real tokens only (no padding mask needed)."""

    def __init__(self, block: nn.Module, gates: th.Tensor | None, activation: str):
        super().__init__()
        attention = block.attention
        self.n_heads = attention.n_heads
        self.head_dim = attention.head_dim
        self.norm1 = copy.deepcopy(block.norm1)
        self.norm2 = copy.deepcopy(block.norm2)
        self.q, self.k, self.v, self.o = (merged_layer(getattr(attention, n), gates) for n in "qkvo")
        self.ff_in = merged_layer(block.ff_in, gates)
        self.ff_out = merged_layer(block.ff_out, gates)
        self.gelu = activation == "gelu"

    def _heads(self, x: th.Tensor) -> th.Tensor:
        return x.reshape(x.shape[0], x.shape[1], self.n_heads, self.head_dim).transpose(1, 2)

    def forward(self, x: th.Tensor) -> th.Tensor:
        h = self.norm1(x)
        attended = F.scaled_dot_product_attention(self._heads(self.q(h)), self._heads(self.k(h)), self._heads(self.v(h)))
        x = x + self.o(attended.transpose(1, 2).reshape(x.shape))
        hidden = self.ff_in(self.norm2(x))
        hidden = F.gelu(hidden) if self.gelu else F.relu(hidden)
        return x + self.ff_out(hidden)


class CompactActor(DeployedActor):
    """Deterministic actor of one DivMorph student for one robot and one task.

    ``forward(proprioceptive, hfield, goal, object)`` takes the env's *raw* observation arrays,
    batched: (B, 12, 52), (B, 1410), (B, 3), (B, 12) (inputs the task does not use are ignored),
    and returns the (B, 24) action means (0 on padded slots), equal to the student's deterministic
    action before clipping to [-1, 1].

    Build it with :meth:`from_policy`.
    """

    def __init__(self) -> None:
        super().__init__()
        self.real_tokens: th.Tensor
        self.action_scale: th.Tensor

    @classmethod
    @th.no_grad()
    def from_policy(
        cls,
        policy: nn.Module,
        observation: Mapping[str, np.ndarray],
        observation_keys: tuple[str, ...],
        normalizer: Any | None = None,
    ) -> CompactActor:
        """Prune and merge a DivMorph (or MetaMorph) policy for the robot and task of ``observation``.

        :param policy: the student (``DivMorphPolicy``; a ``MetaMorphPolicy`` works too, only folded).
        :param observation: one raw observation (unbatched) of the robot doing the task.
        :param observation_keys: the task observations the task provides
            (``unimal_envs.tasks.TASKS[name].observation_keys``); the other exteroception keys
            are constant zeros and their encoders are folded away.
        :param normalizer: the student's ``VecNormalize`` (statistics baked in), or ``None``.
        """
        self = cls()
        policy = policy.cpu().eval()
        raw = {k: np.asarray(v, dtype=np.float32)[None] for k, v in observation.items()}
        normalized = raw if normalizer is None else normalizer.normalize_obs(raw)
        obs = {k: th.as_tensor(v) for k, v in normalized.items()}
        gates = policy.tailor_gates(obs) if hasattr(policy, "tailor_gates") else None
        gates = None if gates is None else gates[0:1]
        extractor = policy.features_extractor if policy.share_features_extractor else policy.pi_features_extractor

        real = th.nonzero(obs[OBS_PADDING_MASK][0] < 0.5).flatten()
        self.register_buffer("real_tokens", real)
        self.n_tokens = int(obs[OBS_PADDING_MASK].shape[1])
        self.slots = policy.slots_per_token

        # Normalisation of the inputs that stay inputs (baked VecNormalize statistics).
        self.used_extero = [k for k in extractor.exteroception.keys() if k in observation_keys]
        self.bake_normalization(normalizer, real, self.used_extero)

        # Token embedding: the context rows, bias and position embedding are constants.
        embedding = extractor.embedding
        proprio_dim = obs[PROPRIOCEPTIVE].shape[-1]
        weight = embedding.linear.weight
        constant = embedding.linear.bias.expand(len(real), -1).clone()
        if extractor.use_context:
            constant += obs[CONTEXT][0, real] @ weight[:, proprio_dim:].T
        self.embed = _frozen_linear(weight[:, :proprio_dim] * embedding.scale, None)
        self.token_bias = nn.Parameter(constant * embedding.scale + embedding.position[real], requires_grad=False)

        activation = "gelu" if extractor.encoder.layers and extractor.encoder.layers[0].activation is F.gelu else "relu"
        self.blocks = nn.ModuleList(
            CompactBlock(block, None if gates is None else gates[0], activation) for block in extractor.encoder.layers
        )
        tailor = None if gates is None else gates[0]
        self.exteroception = nn.ModuleDict({k: merged_encoder(extractor.exteroception[k], tailor) for k in self.used_extero})

        # Exteroception encodings of the task's missing observations are constants: fold them
        # into the first decoder layer's bias.
        extero_const = {
            k: encoder(obs[k].flatten(1), gates)[0] for k, encoder in extractor.exteroception.items() if k not in self.used_extero
        }
        d_model = extractor.d_model
        pieces, keep, offset = [], [th.arange(d_model)], d_model
        for key, encoder in extractor.exteroception.items():
            width = encoder.out_dim
            if key in extero_const:
                pieces.append((offset, extero_const[key]))
            else:
                keep.append(th.arange(offset, offset + width))
            offset += width
        keep_rows = th.cat(keep)
        full_input = th.zeros(offset)
        for start, value in pieces:
            full_input[start : start + len(value)] = value
        dropped_values = full_input[~th.isin(th.arange(offset), keep_rows)]

        decoder_layers = list(policy.mlp_extractor.policy_net.layers) + [policy.action_net]
        first = merged_layer(decoder_layers[0], tailor, keep_rows, dropped_values)
        self.decoder = nn.ModuleList([first] + [merged_layer(layer, tailor) for layer in decoder_layers[1:]])
        # the decoder's own activation modules (after every hidden layer, none after the head)
        self.decoder_activations = nn.ModuleList(copy.deepcopy(list(policy.mlp_extractor.policy_net.activations)) + [nn.Identity()])

        slot_real = (obs[ACT_PADDING_MASK][0] < 0.5).float().view(self.n_tokens, self.slots)
        self.register_buffer("action_scale", slot_real[real])
        # a deployed actor is not trained: its outputs convert to numpy without torch.no_grad()
        self.requires_grad_(False)
        return self.eval()

    def forward(self, proprioceptive: th.Tensor, hfield: th.Tensor, goal: th.Tensor, object: th.Tensor) -> th.Tensor:  # noqa: A002
        tokens = self._normalize(PROPRIOCEPTIVE, proprioceptive.index_select(1, self.real_tokens))
        x = self.embed(tokens) + self.token_bias
        for block in self.blocks:
            x = block(x)
        return self._fuse_and_decode(x, hfield, goal, object)


def actor_parameter_count(policy: nn.Module) -> int:
    """Numbers a policy's actor needs at inference (extractor, decoder, head, router, std, and the
    SVD bases of Cayley-parametrised factors)."""
    counts = policy.parameter_counts()
    prefix = "shared" if policy.share_features_extractor else "actor"
    total = sum(v for k, v in counts.items() if k.startswith((prefix + "/", "router/")))
    if policy.share_features_extractor:
        total += counts["actor/decoder"] + counts["actor/log_std"]
    return total


def export_torchscript(actor: CompactActor, example: Mapping[str, np.ndarray], path: str | Path, metadata: Mapping[str, Any]) -> Path:
    """Trace ``actor`` on one example observation and write TorchScript to ``path`` atomically.

    ``metadata`` is stored inside the archive (``torch.jit.load(path, _extra_files={"metadata.json": ""})``).
    """
    path = Path(path)
    traced = th.jit.trace(actor, actor_inputs(example), check_trace=False)
    buffer = io.BytesIO()
    th.jit.save(traced, buffer, _extra_files={"metadata.json": json.dumps(dict(metadata), indent=1)})
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(buffer.getvalue())
    tmp.replace(path)
    return path


def metamorph_twin(policy: nn.Module) -> nn.Module:
    """A MetaMorph policy of the same width, depth and encoders as a DivMorph student (random init):
    the paper's size reference."""
    from sb3_divmorph.policies.morphology_transformer import MetaMorphPolicy

    return MetaMorphPolicy(policy.observation_space, policy.action_space, lambda _: 0.0, **policy.metamorph_kwargs())


def size_comparison(
    policy: nn.Module,
    compact: CompactActor,
    observation: Mapping[str, np.ndarray],
    observation_keys: tuple[str, ...],
    normalizer: Any | None = None,
) -> dict[str, float]:
    """Like-for-like sizes: the compact actor against the MetaMorph actor of the same task and
    sizes exported through the *same* folding (:class:`CompactActor`), so that pruning is credited
    with what pruning removes and folding is reported on its own.

    :return: ``metamorph_actor`` (stored parameters of the unfolded MetaMorph actor),
        ``metamorph_folded`` (its folded export), ``compact`` (this actor's), ``folding`` =
        unfolded / folded MetaMorph, ``reduction`` = folded MetaMorph / compact (like for like).
    """
    twin = metamorph_twin(policy) if hasattr(policy, "router") else policy
    folded = CompactActor.from_policy(twin, observation, observation_keys, normalizer).stored_numbers()["weights"]
    unfolded = actor_parameter_count(twin)
    ours = compact.stored_numbers()["weights"]
    return {
        "metamorph_actor": unfolded,
        "metamorph_folded": folded,
        "compact": ours,
        "folding": unfolded / folded,
        "reduction": folded / ours,
    }


def batch1_latency(fn, inputs: tuple, repeats: int = 200, warmup: int = 20) -> float:
    """Median seconds of one call of ``fn(*inputs)`` (no grad)."""
    with th.no_grad():
        for _ in range(warmup):
            fn(*inputs)
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn(*inputs)
            times.append(time.perf_counter() - start)
    return statistics.median(times)
