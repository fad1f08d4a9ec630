"""Per-token decoders: the ``mlp_extractor`` and output heads of the morphology-aware policies.

Every token is decoded by the same weights, so a (B, L, F) feature tensor maps to (B, L, out).
The hidden layers follow SB3's ``net_arch`` convention (``dict(pi=[...], vf=[...])``), which also
keeps rl-zoo's hyperparameter sampler (it only sets ``net_arch`` and ``activation_fn``) working.
"""

from __future__ import annotations

import torch as th
from torch import nn

from sb3_divmorph.nn.layers import LinearBuilder


def small_uniform_init(layer: nn.Linear) -> None:
    """MetaMorph's output-layer init: weight U(-0.01, 0.01), zero bias."""
    nn.init.uniform_(layer.weight, -0.01, 0.01)
    nn.init.zeros_(layer.bias)


class TokenMLP(nn.Module):
    """Per-token MLP whose layers may be factorized and gated.

    :param in_dim: token feature size.
    :param dims: layer widths; the activation follows every layer unless ``final_activation``
        is False.
    :param builder: builds each layer.
    :param activation_fn: activation class.
    :param final_activation: apply the activation after the last layer too.
    :param last_init: initialiser of the last layer's dense init (e.g. :func:`small_uniform_init`).
    :param name: prefix of the layers' names in errors.
    """

    def __init__(
        self,
        in_dim: int,
        dims: list[int],
        builder: LinearBuilder,
        activation_fn: type[nn.Module] = nn.ReLU,
        final_activation: bool = True,
        last_init=None,
        name: str = "decoder",
    ):
        super().__init__()
        layers = []
        for i, out_dim in enumerate(dims):
            is_last = i == len(dims) - 1
            layers.append(builder(in_dim, out_dim, last_init if is_last else None, name=f"{name}.{i}"))
            in_dim = out_dim
        self.layers = nn.ModuleList(layers)
        self.activations = nn.ModuleList(
            activation_fn() if (i < len(dims) - 1 or final_activation) else nn.Identity() for i in range(len(dims))
        )
        self.out_dim = in_dim

    def forward(self, x: th.Tensor, tailor_gates: th.Tensor | None = None) -> th.Tensor:
        for layer, activation in zip(self.layers, self.activations):
            x = activation(layer(x, tailor_gates))
        return x


class TokenDecoder(nn.Module):
    """SB3 ``mlp_extractor`` for token features: separate actor and critic per-token MLPs.

    :param features_dim: token feature size from the extractor.
    :param net_arch: ``dict(pi=[...], vf=[...])`` hidden widths (a list means the same for both).
    :param activation_fn: activation class.
    :param actor_builder: builds the actor's layers (factorized for DivMorph).
    :param critic_builder: builds the critic's layers.
    """

    def __init__(
        self,
        features_dim: int,
        net_arch: list[int] | dict[str, list[int]],
        activation_fn: type[nn.Module],
        actor_builder: LinearBuilder,
        critic_builder: LinearBuilder,
    ):
        super().__init__()
        if isinstance(net_arch, dict):
            pi_dims, vf_dims = net_arch.get("pi", []), net_arch.get("vf", [])
        else:
            pi_dims = vf_dims = net_arch
        self.policy_net = TokenMLP(features_dim, list(pi_dims), actor_builder, activation_fn, name="actor decoder")
        self.value_net = TokenMLP(features_dim, list(vf_dims), critic_builder, activation_fn, name="critic decoder")
        self.latent_dim_pi = self.policy_net.out_dim
        self.latent_dim_vf = self.value_net.out_dim

    def forward(self, features: th.Tensor, tailor_gates: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        return self.forward_actor(features, tailor_gates), self.forward_critic(features, tailor_gates)

    def forward_actor(self, features: th.Tensor, tailor_gates: th.Tensor | None = None) -> th.Tensor:
        return self.policy_net(features, tailor_gates)

    def forward_critic(self, features: th.Tensor, tailor_gates: th.Tensor | None = None) -> th.Tensor:
        return self.value_net(features, tailor_gates)
