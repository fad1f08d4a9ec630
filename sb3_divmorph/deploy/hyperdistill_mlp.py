"""HyperDistill deployed for one robot: the MLP its hypernetwork writes, generated once (:class:`HyperDistillMLP`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch as th
from torch import nn

from sb3_divmorph.deploy.deployment import DeployedActor
from sb3_divmorph.nn.extractors import ACT_PADDING_MASK, CONTEXT, PROPRIOCEPTIVE, token_padding
from sb3_divmorph.policies.hyperdistill import TASK_INDEX, HyperDistillNetwork, HyperDistillPolicy


class HyperDistillMLP(DeployedActor):
    """The MLP a HyperDistill student writes for one robot: a plain ``nn.Module``, generated once.

    ``forward(proprioceptive, hfield, goal, object)`` on raw (B, 12, 52), (B, 1410), (B, 3), (B, 12)
    arrays -> (B, 24) action means (0 on padded slots), like
    :class:`~sb3_divmorph.deploy.compact.CompactActor`. Layers: ``Linear(n*52 -> H)`` over the robot's real
    limbs (the per-limb input weights stacked), ReLU, exteroception encoders of the task's
    observations concatenated (those of absent observations folded into the next bias),
    ``n_layers - 1`` x (``Linear(H -> H)``, ReLU), ``Linear(H -> n*2)``.
    """

    @classmethod
    @th.no_grad()
    def from_policy(
        cls,
        policy: HyperDistillPolicy,
        observation: Mapping[str, np.ndarray],
        observation_keys: tuple[str, ...],
        normalizer: Any | None = None,
    ) -> HyperDistillMLP:
        """
        :param policy: the trained student.
        :param observation: one raw (unbatched) observation of the robot doing the task (with a task input,
            its ``task_index`` picks the task the MLP is written for).
        :param observation_keys: the task's observations; encoders of the others are folded away.
        :param normalizer: the student's ``VecNormalize`` (statistics baked in), or ``None`` (raw
            observations; a student with its teachers' statistics bakes in those of the observation's task).
        :raises ValueError: the robot has more tokens than the student supports.
        """
        if not isinstance(policy, HyperDistillPolicy):
            raise TypeError(f"HyperDistillMLP needs a HyperDistillPolicy, got {type(policy).__name__}")
        net: HyperDistillNetwork = policy.network
        for key in (PROPRIOCEPTIVE, CONTEXT):
            net.check_tokens(np.shape(observation[key])[0], f"the robot's {key}")
        self = cls()
        policy = policy.cpu().eval()
        if policy.observation_statistics == "teachers":  # the statistics of the teacher of this task
            if normalizer is not None:
                raise ValueError("this student normalises with its teachers' statistics; pass normalizer=None")
            normalizer = policy.task_normalizer(int(np.round(np.asarray(observation[TASK_INDEX]).reshape(-1)[0])))
        raw = {k: np.asarray(v, dtype=np.float32)[None] for k, v in observation.items()}
        obs = {k: th.as_tensor(v) for k, v in (raw if normalizer is None else normalizer.normalize_obs(raw)).items()}
        padding = token_padding(obs)
        real = th.nonzero(~padding[0]).flatten()
        self.register_buffer("real_tokens", real)
        self.n_tokens, self.slots = net.n_tokens, net.slots
        self.used_extero = [k for k in net.exteroception.keys() if k in observation_keys]
        self.bake_normalization(normalizer, real, self.used_extero)

        context = net.context_input(obs, padding)  # with a task input: the MLP of this robot doing this task
        weights = net.generate(net._encode(context, padding))
        S = net.slots
        rows, cols = net.real_indices(real)
        self.input = _linear(weights.w_in[0][rows], weights.b_in[0])
        # the layer after the input layer reads [h, extero]: fold the absent observations' encodings
        extero_layers = [(k, e) for k, e in net.exteroception.items()]
        after = list(weights.hidden) + [(weights.w_out, weights.b_out)]
        w_next, b_next = after[0][0][0], after[0][1][0].clone()
        keep, offset = [th.arange(net.hidden_dim)], net.hidden_dim
        for key, encoder in extero_layers:
            if key in self.used_extero:
                keep.append(th.arange(offset, offset + encoder.out_dim))
            else:
                b_next += encoder(obs[key].flatten(1))[0] @ w_next[offset : offset + encoder.out_dim]
            offset += encoder.out_dim
        w_next = w_next[th.cat(keep)]
        layers = [(w_next, b_next)] + [(w[0], b[0]) for w, b in after[1:]]
        layers[-1] = (layers[-1][0][:, cols], layers[-1][1][cols])
        self.layers = nn.ModuleList(_linear(w, b) for w, b in layers)
        self.exteroception = nn.ModuleDict({k: _frozen_copy(net.exteroception[k]) for k in self.used_extero})
        slot_real = (obs[ACT_PADDING_MASK][0] < 0.5).float().view(self.n_tokens, S)[real].flatten()
        self.register_buffer("action_scale", slot_real)
        return self.eval()

    def forward(self, proprioceptive: th.Tensor, hfield: th.Tensor, goal: th.Tensor, object: th.Tensor) -> th.Tensor:  # noqa: A002
        inputs = {"hfield": hfield, "goal": goal, "object": object}
        x = self._normalize(PROPRIOCEPTIVE, proprioceptive.index_select(1, self.real_tokens))
        h = th.relu(self.input(x.flatten(1)))
        if self.used_extero:
            h = th.cat([h] + [self.exteroception[k](self._normalize(k, inputs[k].flatten(1))) for k in self.used_extero], dim=-1)
        for i, layer in enumerate(self.layers):
            h = layer(h)
            if i < len(self.layers) - 1:
                h = th.relu(h)
        actions = (h * self.action_scale).view(h.shape[0], -1, self.slots)
        out = h.new_zeros(h.shape[0], self.n_tokens, self.slots)
        return out.index_copy(1, self.real_tokens, actions).flatten(1)


def _linear(weight_in_out: th.Tensor, bias: th.Tensor) -> nn.Linear:
    layer = nn.Linear(weight_in_out.shape[0], weight_in_out.shape[1])
    layer.weight = nn.Parameter(weight_in_out.T.detach().clone().contiguous(), requires_grad=False)
    layer.bias = nn.Parameter(bias.detach().clone(), requires_grad=False)
    return layer


def _frozen_copy(module: nn.Module) -> nn.Module:
    import copy

    module = copy.deepcopy(module)
    for p in module.parameters():
        p.requires_grad_(False)
    return module
