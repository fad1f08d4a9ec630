"""MetaMorph and DivMorph policies for Stable-Baselines3 (``ActorCriticPolicy`` subclasses).

Both read the UNIMAL observation dict (see ``unimal_envs.contract``): per-limb tokens with a
key-padding mask, exteroception, and a padded action vector with its own mask.

* :class:`MetaMorphPolicy`: MetaMorph's morphology-aware Transformer. Separate actor and critic
  Transformers by default (``share_features_extractor=False``), per-token decoders, value = mean of
  per-token values over real tokens, masked Gaussian with a fixed std of 0.9.
* :class:`DivMorphPolicy`: the same network with every Transformer projection and decoder layer
  factorized into rank-1 units, split into learngenes and morphology/task tailors that per-sample
  ``softmax(TopK)`` gates switch on (knowledge diversion).

Sizes come from a named preset (``"small"``: sized for a 2-core CPU; ``"paper"``: MetaMorph's
5 layers x width 128, 2 heads, FFN 1024; ``"metamorph"``: the paper sizes with the rest of
MetaMorph's reference settings too) and any keyword given explicitly overrides it.
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.distributions import Distribution
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.preprocessing import preprocess_obs
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_divmorph.nn.decoders import TokenDecoder, small_uniform_init
from sb3_divmorph.nn.distributions import MaskedDiagGaussianDistribution
from sb3_divmorph.nn.fused import FusedTowers
from sb3_divmorph.nn.extractors import (
    ACT_PADDING_MASK,
    CONTEXT,
    OBS_PADDING_MASK,
    PROPRIOCEPTIVE,
    TASK_EMBEDDING,
    MorphologyTransformerExtractor,
    token_padding,
)
from sb3_divmorph.nn.gates import DiversionRouter, GateActivations, masked_mean
from sb3_divmorph.nn.layers import Factorization, LinearBuilder, batched_square_factors
from sb3_divmorph.nn.transformer import TokenEmbedding, TokenPacking, TransformerEncoder, packing_for

#: What the project's presets add to MetaMorph's network (each an option of the policies): a
#: 35-feature morphology ``context`` row in every token, a hidden layer in the per-token decoders,
#: and no embedding dropout.
_PROJECT_DEFAULTS: dict[str, Any] = dict(
    dropout=0.0,
    embedding_dropout=0.0,
    embedding_dropout_in_rollouts=False,
    transformer_activation="relu",
    use_context=True,
)

#: Network settings shared by the policies.
PRESETS: dict[str, dict[str, Any]] = {
    # ~40x cheaper than "paper" per sample: trains at a few hundred steps/s on 2 CPU cores.
    "small": dict(
        d_model=64,
        n_layers=2,
        n_heads=2,
        ff_dim=512,
        net_arch=dict(pi=[64], vf=[64]),
        exteroception=dict(hfield=[32, 32], goal=[16], object=[16]),
        **_PROJECT_DEFAULTS,
    ),
    # MetaMorph's sizes (unimal_spec.md 6.1); decoder hidden [64] is MetaMorph's VT decoder.
    "paper": dict(
        d_model=128,
        n_layers=5,
        n_heads=2,
        ff_dim=1024,
        net_arch=dict(pi=[64], vf=[64]),
        exteroception=dict(hfield=[64, 64], goal=[32], object=[32]),
        **_PROJECT_DEFAULTS,
    ),
    # MetaMorph as its reference code (agrimgupta92/metamorph, configs/ft.yaml and config.py) builds
    # it: the paper sizes, dropout 0.1 after the position embedding -- applied in rollouts too, since
    # that code never puts its model in eval mode (deterministic evaluation here stays without it) --,
    # no input beyond the proprioception (its hardware features included) and a linear per-token
    # decoder (FT's DECODER_DIMS = []; its VT config has [64], Obstacle [64, 64]: give net_arch).
    "metamorph": dict(
        d_model=128,
        n_layers=5,
        n_heads=2,
        ff_dim=1024,
        net_arch=dict(pi=[], vf=[]),
        exteroception=dict(hfield=[64, 64], goal=[32], object=[32]),
        dropout=0.0,
        embedding_dropout=0.1,
        embedding_dropout_in_rollouts=True,
        transformer_activation="relu",
        use_context=False,
    ),
}
#: The preset whose sizes a derived preset takes in the other policies' own tables.
PRESET_SIZES = {"small": "small", "paper": "paper", "metamorph": "paper"}

#: DivMorph's diversion sizes per preset: a quarter of each d_model-rank layer is tailors, half
#: of each tailor group active per sample.
DIVMORPH_PRESETS: dict[str, dict[str, Any]] = {
    "small": dict(
        n_morph_tailors=8,
        n_task_tailors=8,
        top_k_morph=4,
        top_k_task=4,
        morph_embed_dim=32,
        morph_encoder_layers=1,
        gate_hidden_dim=64,
    ),
    "paper": dict(
        n_morph_tailors=16,
        n_task_tailors=16,
        top_k_morph=8,
        top_k_task=8,
        morph_embed_dim=64,
        morph_encoder_layers=1,
        gate_hidden_dim=128,
    ),
}


#: Named diversion configurations (``DivMorphPolicy(diversion=NAME)``), built for deployment: few
#: always-on units (``n_learngenes`` per layer, tailors sized per layer from the rest of its rank)
#: and a TopK of 1-2 per gate, with the exteroception encoders diverted too, so that pruning keeps
#: only a handful of units per layer. ``n_morph_tailors`` / ``n_task_tailors`` left out here
#: default to half of the ``d_model``-rank layers' free units each (see :meth:`DivMorphPolicy.config`).
DIVERSIONS: dict[str, dict[str, Any]] = {
    "default": {},
    "deploy-g4k2": dict(n_learngenes=4, top_k_morph=2, top_k_task=2, divert_exteroception=True),
    "deploy-g2k1": dict(n_learngenes=2, top_k_morph=1, top_k_task=1, divert_exteroception=True),
    "deploy-g1k1": dict(n_learngenes=1, top_k_morph=1, top_k_task=1, divert_exteroception=True),
}


def _resolve(preset_table: Mapping[str, Mapping[str, Any]], preset: str, explicit: Mapping[str, Any]) -> dict[str, Any]:
    if preset not in preset_table:
        raise ValueError(f"Unknown preset {preset!r}; choose from {sorted(preset_table)}")
    config = copy.deepcopy(dict(preset_table[preset]))
    config.update({key: value for key, value in explicit.items() if value is not None})
    return config


class MorphologyTransformerPolicy(ActorCriticPolicy):
    """Base class of :class:`MetaMorphPolicy` and :class:`DivMorphPolicy`.

    :param observation_space: the UNIMAL ``spaces.Dict``.
    :param action_space: ``Box(-1, 1, (L * slots,))``, two slots per token.
    :param lr_schedule: learning-rate schedule.
    :param preset: ``"small"`` (default) or ``"paper"``; explicit keywords override it.
    :param d_model: token width.
    :param n_layers: Transformer layers.
    :param n_heads: attention heads.
    :param ff_dim: Transformer FFN width.
    :param dropout: Transformer dropout (the preset's: 0, see the extractor).
    :param embedding_dropout: dropout after the position embedding (the preset's: 0, ``metamorph`` 0.1).
    :param embedding_dropout_in_rollouts: keep the embedding dropout on when actions are sampled for
        training (:meth:`forward`, which collects rollouts, with the policy in eval mode), as
        MetaMorph's code does; :meth:`predict` (deterministic evaluation, deployment) never drops.
        The preset's: off, ``metamorph`` on.
    :param transformer_activation: ``"relu"`` (MetaMorph) or ``"gelu"``.
    :param use_context: feed ``context`` into each token next to ``proprioceptive`` (the preset's:
        on, ``metamorph`` off).
    :param exteroception: ``{key: MLP widths}`` of the late-fused global encoders.
    :param action_std: standard deviation of the Gaussian (MetaMorph: fixed 0.9); the initial value
        if ``learn_std``.
    :param learn_std: learn a state-independent log-std per action slot.
    :param mixed_precision: run the token embedding, the exteroception encoders and the Transformer
        (nearly all of a forward pass's FLOPs) under bfloat16 autocast, in rollouts and updates alike;
        the gates, Cayley maps, per-token decoders, heads, log-probabilities, values and the optimiser
        stay float32 (the features are cast back before the decoders). Off by default: a GPU option,
        whose effect on actions and gradients is measured by ``benchmarks/mixed_precision.py``.
    :param kwargs: ``ActorCriticPolicy`` arguments. ``net_arch`` gives the per-token decoder's
        hidden widths, ``activation_fn`` its activation (default ``nn.ReLU``);
        ``share_features_extractor`` defaults to False (separate actor and critic Transformers,
        as in MetaMorph). ``ortho_init`` must stay False: it would overwrite the Transformer and
        SVD initialisations.
    """

    preset_table: dict[str, dict[str, Any]] = PRESETS
    #: run a rollout step's actor and critic as one stacked pass where the towers allow it (towers of the same
    #: sizes with a dense critic: MetaMorph, DivMorph); ``False`` runs them one after the other (the same latents
    #: up to float rounding)
    fuse_rollout_towers: bool = True
    #: whether ``mixed_precision=True`` is implemented for this policy's feature extractors
    supports_mixed_precision: bool = True
    #: observation keys the policy reads besides the per-token ones
    required_keys: tuple[str, ...] = ()
    _config_keys: tuple[str, ...] = (
        "d_model",
        "n_layers",
        "n_heads",
        "ff_dim",
        "dropout",
        "embedding_dropout",
        "embedding_dropout_in_rollouts",
        "transformer_activation",
        "use_context",
        "exteroception",
    )

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        preset: str = "small",
        d_model: int | None = None,
        n_layers: int | None = None,
        n_heads: int | None = None,
        ff_dim: int | None = None,
        dropout: float | None = None,
        embedding_dropout: float | None = None,
        embedding_dropout_in_rollouts: bool | None = None,
        transformer_activation: str | None = None,
        use_context: bool | None = None,
        exteroception: Mapping[str, Sequence[int]] | None = None,
        action_std: float = 0.9,
        learn_std: bool = False,
        mixed_precision: bool = False,
        **kwargs: Any,
    ):
        if mixed_precision and not self.supports_mixed_precision:
            raise ValueError(f"{type(self).__name__} does not support mixed_precision=True (its extractors are not autocast-safe yet)")
        self.mixed_precision = bool(mixed_precision)
        explicit = dict(
            d_model=d_model,
            n_layers=n_layers,
            n_heads=n_heads,
            ff_dim=ff_dim,
            dropout=dropout,
            embedding_dropout=embedding_dropout,
            embedding_dropout_in_rollouts=embedding_dropout_in_rollouts,
            transformer_activation=transformer_activation,
            use_context=use_context,
            exteroception=exteroception,
            net_arch=kwargs.get("net_arch"),
        )
        explicit.update(self._extra_explicit())
        self.preset = preset
        self.config = _resolve(self.preset_table, preset, explicit)
        self.action_std = float(action_std)
        self.learn_std = learn_std

        if kwargs.get("use_sde"):
            raise ValueError(f"{type(self).__name__} does not support gSDE")
        if kwargs.setdefault("ortho_init", False):
            raise ValueError("ortho_init=True would overwrite the Transformer/SVD initialisation")
        expected_log_std = math.log(self.action_std)
        if not math.isclose(kwargs.setdefault("log_std_init", expected_log_std), expected_log_std, abs_tol=1e-9):
            raise ValueError("Set the Gaussian's std with action_std (and learn_std), not log_std_init")
        kwargs["net_arch"] = self.config.pop("net_arch")
        kwargs.setdefault("activation_fn", nn.ReLU)
        kwargs.setdefault("share_features_extractor", False)
        kwargs.setdefault("features_extractor_class", MorphologyTransformerExtractor)
        kwargs["features_extractor_kwargs"] = {**self._extractor_kwargs(), **(kwargs.get("features_extractor_kwargs") or {})}

        if not isinstance(observation_space, spaces.Dict) or PROPRIOCEPTIVE not in observation_space.spaces:
            raise ValueError(f"{type(self).__name__} needs the UNIMAL Dict observation space")
        needed = (OBS_PADDING_MASK, ACT_PADDING_MASK, *self.required_keys)
        missing = [key for key in needed if key not in observation_space.spaces]
        if missing:
            raise ValueError(f"{type(self).__name__} needs the observation keys {missing}")
        n_tokens = observation_space[PROPRIOCEPTIVE].shape[0]
        if len(action_space.shape) != 1 or action_space.shape[0] % n_tokens:
            raise ValueError(f"Action size {action_space.shape} is not a multiple of the {n_tokens} tokens")
        self.n_tokens = n_tokens
        self.slots_per_token = action_space.shape[0] // n_tokens
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)

    # -- hooks for DivMorph --------------------------------------------------------------------
    def _extra_explicit(self) -> dict[str, Any]:
        """Subclass-specific keyword values (``None`` = take the preset's)."""
        return {}

    def _extractor_kwargs(self) -> dict[str, Any]:
        c = self.config
        return dict(
            d_model=c["d_model"],
            n_layers=c["n_layers"],
            n_heads=c["n_heads"],
            ff_dim=c["ff_dim"],
            dropout=c["dropout"],
            embedding_dropout=c["embedding_dropout"],
            activation=c["transformer_activation"],
            use_context=c["use_context"],
            exteroception=c["exteroception"],
        )

    def _decoder_builder(self) -> LinearBuilder:
        """Builder of the actor's per-token decoder layers and action head."""
        return LinearBuilder()

    def _critic_builder(self) -> LinearBuilder:
        """Builder of the critic's per-token decoder layers and value head."""
        return self._decoder_builder()

    def _rebuild_critic_extractor(self) -> None:
        """Replace the critic's extractor if it must differ from the actor's (DivMorph)."""

    def _build_router(self) -> None:
        """Build any module that conditions the network (none for MetaMorph)."""

    def tailor_gates(self, obs: Mapping[str, th.Tensor]) -> th.Tensor | None:
        """(B, N_m + N_t) per-sample gates of a batch of (preprocessed) observation tensors, in the
        order tailors sit in every diverted layer, as the layers take them; ``None`` for an ungated
        network (MetaMorph, or DivMorph with every diversion ablated). Computed with grad, as training
        routes through them (DivMorph's ``get_gates`` is the no-grad view of both gates apart)."""
        return None

    # -- construction --------------------------------------------------------------------------
    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update({key: self.config[key] for key in self._config_keys})
        data.update(
            preset=self.preset,
            action_std=self.action_std,
            learn_std=self.learn_std,
            mixed_precision=self.mixed_precision,
            share_features_extractor=self.share_features_extractor,
        )
        return data

    def _build_mlp_extractor(self) -> None:
        self.mlp_extractor = TokenDecoder(
            self.features_dim, self.net_arch, self.activation_fn, self._decoder_builder(), self._critic_builder()
        )

    def _build(self, lr_schedule: Schedule) -> None:
        # Replaces SB3's _build entirely: per-token heads, masked distribution, no orthogonal
        # re-init, and the optimizer is created once, over the final set of modules.
        self.action_dist = MaskedDiagGaussianDistribution(int(np.prod(self.action_space.shape)))
        self._rebuild_critic_extractor()
        self._build_mlp_extractor()
        # the output heads (2 actions, 1 value per token) have no room for tailors: never diverted
        self.action_net = self._decoder_builder()(
            self.mlp_extractor.latent_dim_pi, self.slots_per_token, small_uniform_init, name="action head", divert=False
        )
        self.value_net = self._critic_builder()(self.mlp_extractor.latent_dim_vf, 1, small_uniform_init, name="value head", divert=False)
        log_std = th.full((self.action_dist.action_dim,), math.log(self.action_std))
        if self.learn_std:
            self.log_std = nn.Parameter(log_std)
        else:
            self.register_buffer("log_std", log_std)
        self._build_router()
        self.optimizer = self.optimizer_class(  # type: ignore[call-arg]
            self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )

    # -- forward passes ------------------------------------------------------------------------
    def _preprocess(self, obs: PyTorchObs) -> dict[str, th.Tensor]:
        processed = preprocess_obs(obs, self.observation_space, normalize_images=self.normalize_images)
        return processed  # type: ignore[return-value]

    def _latents(
        self, obs: Mapping[str, th.Tensor], actor: bool = True, critic: bool = True
    ) -> tuple[th.Tensor | None, th.Tensor | None, th.Tensor | None]:
        """Per-token actor and critic latents, and the tailor gates used by the actor."""
        gates = self.tailor_gates(obs)
        # With separate actor and critic extractors (the default) the router is trained by the
        # policy objective only: the critic's modules see detached gates, so the value loss cannot
        # re-route the actor. With share_features_extractor=True the value loss reaches the router
        # (and every shared weight) through the shared features, as any shared SB3 extractor does.
        critic_gates = None if gates is None else gates.detach()
        fused = self._fused_towers() if actor and critic else None
        if fused is not None and fused.takes(gates):
            return (*fused.latents(obs, gates), gates)
        packing = self._packing(obs)
        if packing is not None:
            return (*self._packed_latents(obs, gates, critic_gates, packing, actor, critic), gates)
        latent_pi = latent_vf = None
        with self._extractor_precision():
            if self.share_features_extractor:
                features = self.features_extractor(obs, gates)
                pi_features = vf_features = features
            else:
                pi_features = self.pi_features_extractor(obs, gates) if actor else None
                vf_features = self.vf_features_extractor(obs, critic_gates) if critic else None
        pi_features, vf_features = _float32(pi_features), _float32(vf_features)
        if actor:
            latent_pi = self.mlp_extractor.forward_actor(pi_features, gates)
        if critic:
            latent_vf = self.mlp_extractor.forward_critic(vf_features, critic_gates)
        return latent_pi, latent_vf, gates

    def _fused_towers(self) -> FusedTowers | None:
        """The one-pass actor and critic (:class:`~sb3_divmorph.nn.fused.FusedTowers`) for this pass: a rollout
        step (no autograd, eval mode, no dropout in it) of a policy whose towers allow it, else ``None``."""
        if th.is_grad_enabled() or self.training or not self.fuse_rollout_towers:
            return None
        if self.config["embedding_dropout_in_rollouts"] and self.config["embedding_dropout"] > 0:
            return None
        fused = self.__dict__.get("_fused")
        current = (self.pi_features_extractor, self.vf_features_extractor, self.mlp_extractor.policy_net, self.mlp_extractor.value_net)
        if fused is None or fused[0] != tuple(map(id, current)):  # first use, or a part replaced since (transfer)
            fused = self.__dict__["_fused"] = (tuple(map(id, current)), FusedTowers.of(self))
        return fused[1]

    def _packing(self, obs: Mapping[str, th.Tensor]) -> TokenPacking | None:
        """The real tokens of ``obs`` when the pass runs packed (autograd recording, packing on: the
        update; see :class:`~sb3_divmorph.nn.transformer.TokenPacking`), else ``None``."""
        extractor = self.features_extractor if self.share_features_extractor else self.pi_features_extractor
        encoder = getattr(extractor, "encoder", None)
        if not isinstance(encoder, TransformerEncoder) or not encoder.pack_tokens:
            return None
        return packing_for(token_padding(obs))

    def _packed_latents(
        self,
        obs: Mapping[str, th.Tensor],
        gates: th.Tensor | None,
        critic_gates: th.Tensor | None,
        packing: TokenPacking,
        actor: bool,
        critic: bool,
    ) -> tuple[th.Tensor | None, th.Tensor | None]:
        """:meth:`_latents`' latents computed on the real tokens only, from the token embedding to the
        per-token decoders' last hidden layer, then padded back (padded tokens' latents zero, which the
        masked distribution and the masked value mean never read)."""
        row_gates = None if gates is None else gates.index_select(0, packing.sample)
        critic_row_gates = None if row_gates is None else row_gates.detach()
        with self._extractor_precision():
            if self.share_features_extractor:
                pi_rows = vf_rows = self.features_extractor.forward_rows(obs, gates, packing)
            else:
                pi_rows = self.pi_features_extractor.forward_rows(obs, gates, packing) if actor else None
                vf_rows = self.vf_features_extractor.forward_rows(obs, critic_gates, packing) if critic else None
        latent_pi = packing.unpack(self.mlp_extractor.forward_actor(_float32(pi_rows), row_gates)) if actor else None
        latent_vf = packing.unpack(self.mlp_extractor.forward_critic(_float32(vf_rows), critic_row_gates)) if critic else None
        return latent_pi, latent_vf

    def _distribution(self, latent_pi: th.Tensor, obs: Mapping[str, th.Tensor], gates: th.Tensor | None) -> MaskedDiagGaussianDistribution:
        mean_actions = self.action_net(latent_pi, gates).flatten(1)
        return self.action_dist.proba_distribution(mean_actions, self.log_std, obs[ACT_PADDING_MASK])

    def _value(self, latent_vf: th.Tensor, obs: Mapping[str, th.Tensor], gates: th.Tensor | None) -> th.Tensor:
        per_token = self.value_net(latent_vf, None if gates is None else gates.detach())
        return masked_mean(per_token, token_padding(obs))

    @contextlib.contextmanager
    def _rollout_dropout(self):
        """Switch the token embeddings' dropout on for one pass of a policy in eval mode, when
        ``embedding_dropout_in_rollouts`` asks for it (see the class docstring)."""
        on = self.config["embedding_dropout_in_rollouts"] and not self.training and self.config["embedding_dropout"] > 0
        modules = [m.dropout for m in self.modules() if isinstance(m, TokenEmbedding)] if on else []
        for module in modules:
            module.train(True)
        try:
            yield
        finally:
            for module in modules:
                module.train(False)

    # Each pass solves the Cayley maps of all its orthogonal factors at once (batched_square_factors).
    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        if th.is_grad_enabled() or th.is_inference_mode_enabled():
            return self._forward(obs, deterministic)
        # A rollout step (SB3 collects under no_grad): inference mode skips autograd's bookkeeping of
        # every op (~15% of a 4-env call). Its outputs are cloned out of it, so that what a caller
        # keeps is an ordinary tensor that a later loss may use.
        with th.inference_mode():
            actions, values, log_prob = self._forward(obs, deterministic)
        return actions.clone(), values.clone(), log_prob.clone()

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        # ``predict`` (evaluation, deployment) runs here under no_grad: inference mode, as in a rollout step
        if th.is_grad_enabled() or th.is_inference_mode_enabled():
            return super()._predict(observation, deterministic)
        with th.inference_mode():
            actions = super()._predict(observation, deterministic)
        return actions.clone()

    def _forward(self, obs: PyTorchObs, deterministic: bool) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        obs = self._preprocess(obs)
        with batched_square_factors(self), self._rollout_dropout():
            latent_pi, latent_vf, gates = self._latents(obs)
            distribution = self._distribution(latent_pi, obs, gates)
            values = self._value(latent_vf, obs, gates)
        actions = distribution.get_actions(deterministic=deterministic)
        log_prob = distribution.log_prob(actions)
        return actions.reshape((-1, *self.action_space.shape)), values, log_prob

    def evaluate_actions(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        obs = self._preprocess(obs)
        with batched_square_factors(self):
            latent_pi, latent_vf, gates = self._latents(obs)
            distribution = self._distribution(latent_pi, obs, gates)
            values = self._value(latent_vf, obs, gates)
        return values, distribution.log_prob(actions), distribution.entropy()

    def get_distribution(self, obs: PyTorchObs) -> Distribution:
        obs = self._preprocess(obs)
        with batched_square_factors(self):
            latent_pi, _, gates = self._latents(obs, critic=False)
            return self._distribution(latent_pi, obs, gates)

    def predict_values(self, obs: PyTorchObs) -> th.Tensor:
        obs = self._preprocess(obs)
        with batched_square_factors(self):
            _, latent_vf, gates = self._latents(obs, actor=False)
            return self._value(latent_vf, obs, gates)

    def extract_features(  # type: ignore[override]
        self, obs: PyTorchObs, features_extractor: nn.Module | None = None
    ) -> th.Tensor | tuple[th.Tensor, th.Tensor]:
        """Token features (B, L, F); a (pi, vf) tuple when the extractor is not shared (SB3's API)."""
        obs = self._preprocess(obs)
        gates = self.tailor_gates(obs)
        with self._extractor_precision():
            if self.share_features_extractor or features_extractor is not None:
                return _float32((features_extractor or self.features_extractor)(obs, gates))
            pi, vf = self.pi_features_extractor(obs, gates), self.vf_features_extractor(obs, None if gates is None else gates.detach())
        return _float32(pi), _float32(vf)

    def _extractor_precision(self) -> th.autocast:
        """bfloat16 autocast around the feature extractors when ``mixed_precision`` (else a no-op)."""
        return th.autocast(self.device.type, dtype=th.bfloat16, enabled=self.mixed_precision)

    # -- analysis ------------------------------------------------------------------------------
    def parameter_counts(self) -> dict[str, int]:
        """Stored numbers per part: parameters, plus the SVD bases of Cayley-parametrised factors
        (``square_base`` buffers, which a DivMorph student needs at inference). A fixed std is
        excluded (it is a constant of the distribution, not of the network)."""

        def count(*modules: nn.Module | None) -> int:
            seen: set[int] = set()
            total = 0
            for module in modules:
                if module is None:
                    continue
                bases = (b for name, b in module.named_buffers() if name.endswith("square_base"))
                for p in (*module.parameters(), *bases):
                    if id(p) not in seen:
                        seen.add(id(p))
                        total += p.numel()
            return total

        parts: dict[str, int] = {}
        if self.share_features_extractor:
            parts.update(self._extractor_parts("shared", self.features_extractor, count))
        else:
            parts.update(self._extractor_parts("actor", self.pi_features_extractor, count))
            parts.update(self._extractor_parts("critic", self.vf_features_extractor, count))
        parts["actor/decoder"] = count(self.mlp_extractor.policy_net, self.action_net)
        parts["critic/decoder"] = count(self.mlp_extractor.value_net, self.value_net)
        parts["actor/log_std"] = self.log_std.numel() if isinstance(self.log_std, nn.Parameter) else 0
        parts.update(self._router_counts(count))
        parts["total"] = count(self)
        return parts

    def _extractor_parts(self, prefix: str, extractor: nn.Module, count) -> dict[str, int]:
        """``parameter_counts`` entries of one extractor (subclasses with other parts override it)."""
        return {
            f"{prefix}/embedding": count(extractor.embedding),
            f"{prefix}/transformer": count(extractor.encoder),
            f"{prefix}/exteroception": count(extractor.exteroception),
        }

    def _router_counts(self, count) -> dict[str, int]:
        return {}


class MetaMorphPolicy(MorphologyTransformerPolicy):
    """MetaMorph's morphology-aware Transformer policy (Gupta et al., ICLR 2022).

    Per-limb tokens (``proprioceptive`` + ``context``) -> linear embedding x sqrt(d) + learnt
    position embedding -> pre-LN Transformer with the key-padding mask -> exteroception (height
    map, goal, object) encodings appended to every token -> per-token decoder: 2 action means per
    token (actor) and 1 value per token averaged over real tokens (critic). Separate actor and
    critic networks unless ``share_features_extractor=True``.

    See :class:`MorphologyTransformerPolicy` for the arguments.
    """


class DivMorphPolicy(MorphologyTransformerPolicy):
    """DivMorph: the MetaMorph network with knowledge diversion (Feng et al., 2025).

    Every Transformer projection (q, k, v, o, FFN in/out) and every decoder layer is a
    :class:`~sb3_divmorph.nn.layers.FactorizedLinear` built from the SVD of its random dense init.
    Per sample, a :class:`~sb3_divmorph.nn.gates.DiversionRouter` encodes ``context`` (morphology) and
    reads ``task_embedding`` (task), and its ``softmax(TopK)`` gates scale the morphology and task
    tailors of every layer; learngenes are always on. Layers whose rank cannot hold the tailors
    plus one learngene (the 2-output action head, the value head) keep every unit a learngene.

    :param n_morph_tailors: ``N_m`` morphology tailors per diverted layer.
    :param n_task_tailors: ``N_t`` task tailors per diverted layer (``N_G = rank - N_m - N_t``).
    :param top_k_morph: tailors kept by the morphology gate.
    :param top_k_task: tailors kept by the task gate.
    :param morph_embed_dim: width of the morphology embedding.
    :param morph_encoder_layers: Transformer layers of the morphology encoder (0 = DeepSets).
    :param gate_hidden_dim: hidden width of the gate MLPs.
    :param orthogonal: Cayley-orthogonal square factors (False: ablation).
    :param divert_transformer: gate the Transformer's tailors (False: ablation; the Transformer
        stays factorized, every unit a learngene).
    :param divert_decoder: gate the decoder's tailors (False: ablation, likewise).
    :param factorize_critic: factorize and gate the critic as well. Default False: the critic is
        MetaMorph's. Distillation never trains a critic, so diverting it would carry no knowledge
        to transfer or deploy, while it would cost as much again as the actor's factorization.
        With ``share_features_extractor=True`` the shared Transformer is the actor's (factorized).
    :param adapter_rank: a zero-initialised low-rank adapter of this width on every factorized
        layer of the actor (0: none; transfer's ``adapter`` recipe builds its model with one and
        trains only the adapters).

    Other arguments: see :class:`MorphologyTransformerPolicy`.
    """

    preset_table = {name: {**PRESETS[name], **DIVMORPH_PRESETS[PRESET_SIZES[name]]} for name in PRESETS}
    required_keys = (CONTEXT, TASK_EMBEDDING)
    _divmorph_keys = (
        "n_morph_tailors",
        "n_task_tailors",
        "top_k_morph",
        "top_k_task",
        "morph_embed_dim",
        "morph_encoder_layers",
        "gate_hidden_dim",
        "orthogonal",
        "divert_transformer",
        "divert_decoder",
        "divert_exteroception",
        "n_learngenes",
        "factorize_critic",
        "adapter_rank",
    )
    _config_keys = MorphologyTransformerPolicy._config_keys + _divmorph_keys

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        preset: str = "small",
        n_morph_tailors: int | None = None,
        n_task_tailors: int | None = None,
        top_k_morph: int | None = None,
        top_k_task: int | None = None,
        morph_embed_dim: int | None = None,
        morph_encoder_layers: int | None = None,
        gate_hidden_dim: int | None = None,
        orthogonal: bool = True,
        divert_transformer: bool = True,
        divert_decoder: bool = True,
        divert_exteroception: bool | None = None,
        n_learngenes: int | None = None,
        factorize_critic: bool = False,
        adapter_rank: int = 0,
        diversion: str = "default",
        **kwargs: Any,
    ):
        if diversion not in DIVERSIONS:
            raise ValueError(f"unknown diversion {diversion!r}; choose from {sorted(DIVERSIONS)}")
        self.diversion = diversion
        named = DIVERSIONS[diversion]
        self._divmorph_explicit = dict(
            n_morph_tailors=n_morph_tailors,
            n_task_tailors=n_task_tailors,
            top_k_morph=top_k_morph,
            top_k_task=top_k_task,
            morph_embed_dim=morph_embed_dim,
            morph_encoder_layers=morph_encoder_layers,
            gate_hidden_dim=gate_hidden_dim,
            orthogonal=orthogonal,
            divert_transformer=divert_transformer,
            divert_decoder=divert_decoder,
            divert_exteroception=divert_exteroception,
            n_learngenes=n_learngenes,
            factorize_critic=factorize_critic,
            adapter_rank=int(adapter_rank),
        )
        # explicit keywords win over the named diversion, which wins over the size preset
        for key, value in named.items():
            if self._divmorph_explicit.get(key) is None:
                self._divmorph_explicit[key] = value
        self._auto_tailors = n_morph_tailors is None and n_task_tailors is None and "n_learngenes" in named
        super().__init__(observation_space, action_space, lr_schedule, preset=preset, **kwargs)

    def _extra_explicit(self) -> dict[str, Any]:
        return self._divmorph_explicit

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "diversion": self.diversion}

    def metamorph_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of a :class:`MetaMorphPolicy` of this policy's width, depth, encoders and
        decoders, without the diversion: ``MetaMorphPolicy(observation_space, action_space, lr_schedule,
        **policy.metamorph_kwargs())`` is the dense network of the same size (deployment's size reference)."""
        kwargs = {k: v for k, v in self._get_constructor_parameters().items() if k not in (*self._divmorph_keys, "diversion")}
        # the extractor kwargs carry DivMorph's factorization; MetaMorph rebuilds its own from the sizes
        for key in ("observation_space", "action_space", "lr_schedule", "features_extractor_kwargs"):
            kwargs.pop(key, None)
        return kwargs

    def _resolve_diversion(self) -> None:
        """Fill the diversion defaults that depend on the network size."""
        c = self.config
        c["divert_exteroception"] = bool(c.get("divert_exteroception") or False)
        c.setdefault("n_learngenes", None)
        if getattr(self, "_auto_tailors", False):
            free = c["d_model"] - c["n_learngenes"]
            c["n_morph_tailors"], c["n_task_tailors"] = free // 2, free - free // 2

    def _factorization(self, divert: bool) -> Factorization:
        c = self.config
        return Factorization(
            c["n_morph_tailors"],
            c["n_task_tailors"],
            orthogonal=c["orthogonal"],
            divert=divert,
            n_learngenes=c["n_learngenes"],
            adapter_rank=c.get("adapter_rank", 0),
        )

    def _extractor_kwargs(self) -> dict[str, Any]:
        self._resolve_diversion()
        f = self._factorization(self.config["divert_transformer"])
        return {
            **super()._extractor_kwargs(),
            "factorization": dict(
                n_morph_tailors=f.n_morph_tailors,
                n_task_tailors=f.n_task_tailors,
                orthogonal=f.orthogonal,
                divert=f.divert,
                n_learngenes=f.n_learngenes,
                adapter_rank=f.adapter_rank,
            ),
            "factorize_exteroception": self.config["divert_exteroception"],
        }

    def _decoder_builder(self) -> LinearBuilder:
        return LinearBuilder(self._factorization(self.config["divert_decoder"]))

    def _critic_builder(self) -> LinearBuilder:
        return self._decoder_builder() if self.config["factorize_critic"] else LinearBuilder()

    def _rebuild_critic_extractor(self) -> None:
        if self.share_features_extractor or self.config["factorize_critic"]:
            return
        kwargs = {**self.features_extractor_kwargs, "factorization": None, "factorize_exteroception": False}
        self.vf_features_extractor = self.features_extractor_class(self.observation_space, **kwargs)

    @property
    def is_gated(self) -> bool:
        """Whether any layer takes gates (False when every diversion is ablated)."""
        c = self.config
        return bool(c["divert_transformer"] or c["divert_decoder"] or (c["divert_exteroception"] and c["exteroception"]))

    def _build_router(self) -> None:
        c = self.config
        self.router = DiversionRouter(
            context_dim=self.observation_space[CONTEXT].shape[-1],
            max_tokens=self.n_tokens,
            task_embedding_dim=int(np.prod(self.observation_space[TASK_EMBEDDING].shape)),
            n_morph_tailors=c["n_morph_tailors"],
            n_task_tailors=c["n_task_tailors"],
            top_k_morph=c["top_k_morph"],
            top_k_task=c["top_k_task"],
            morph_embed_dim=c["morph_embed_dim"],
            morph_encoder_layers=c["morph_encoder_layers"],
            gate_hidden_dim=c["gate_hidden_dim"],
        )

    def _route(self, obs: Mapping[str, th.Tensor]) -> GateActivations:
        return self.router(obs[CONTEXT], token_padding(obs), obs[TASK_EMBEDDING].flatten(1))

    def tailor_gates(self, obs: Mapping[str, th.Tensor]) -> th.Tensor | None:
        return self._route(obs).tailor_gates() if self.is_gated else None

    def get_gates(self, observation: PyTorchObs | dict[str, np.ndarray]) -> GateActivations:
        """Morphology and task gate weights for a batch of observations (analysis, pruning).

        :param observation: observation dict, as numpy arrays (one or a batch) or tensors.
        :return: ``GateActivations(morphology=(B, N_m), task=(B, N_t))`` tensors, no grad.
        """
        if isinstance(next(iter(observation.values())), np.ndarray):
            observation, _ = self.obs_to_tensor(observation)  # type: ignore[arg-type]
        with th.no_grad():
            return self._route(self._preprocess(observation))

    def _router_counts(self, count) -> dict[str, int]:
        return {
            "router/morphology_encoder": count(self.router.morphology_encoder),
            "router/gates": count(self.router.morphology_gate, self.router.task_gate),
        }


def _float32(features: th.Tensor | None) -> th.Tensor | None:
    """Features leaving a (possibly bfloat16 autocast) extractor, as float32 for the decoders."""
    return None if features is None else features.float()
