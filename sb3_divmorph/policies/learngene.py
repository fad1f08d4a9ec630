"""GRL's learngene on a MetaMorph actor: its inheritable whole layers, and copying them into another.

Used by the GRL stage (a child inherits its parent's layers) and by the ``grl`` transfer arm (a new
MetaMorph inherits the evolved learngene); see :mod:`divmorph.pipeline.grl`.
"""

from __future__ import annotations

import torch as th
from torch import nn


def layer_units(policy: nn.Module) -> dict[str, list[nn.Module]]:
    """The inheritable whole layers of a MetaMorph actor, by name (see :mod:`divmorph.pipeline.grl`)."""
    extractor = policy.features_extractor if policy.share_features_extractor else policy.pi_features_extractor
    units: dict[str, list[nn.Module]] = {"embedding": [extractor.embedding]}
    for i, block in enumerate(extractor.encoder.layers):
        units[f"block.{i}"] = [block]
    if len(extractor.exteroception):
        units["exteroception"] = [extractor.exteroception]
    units["decoder"] = [policy.mlp_extractor.policy_net, policy.action_net]
    return units


def unit_tensors(policy: nn.Module, unit: str) -> list[th.Tensor]:
    """Parameters and buffers of one unit, in a fixed order."""
    tensors = []
    for module in layer_units(policy)[unit]:
        tensors += [t for _, t in sorted(module.state_dict(keep_vars=True).items())]
    return tensors


@th.no_grad()
def inherit(child: nn.Module, parent: nn.Module, units: list[str]) -> None:
    """Copy the parent's ``units`` (whole layers) into the child, in place."""
    for unit in units:
        for mine, theirs in zip(unit_tensors(child, unit), unit_tensors(parent, unit), strict=True):
            mine.copy_(theirs)
