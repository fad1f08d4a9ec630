"""HyperDistill (Xiong et al., ICML 2024): a hypernetwork that writes a small MLP controller per robot.

The student maps a robot's ``context`` to the weights of an MLP:

* **input layer**: per limb ``l`` a generated ``W_l`` (limb proprioception -> hidden) and ``b_l``;
  ``h = ReLU(sum_l mask_l (W_l x_l + b_l))`` (a sum over the robot's real limbs);
* the exteroception encodings (``hfield``, ``goal``, ``object`` MLPs, shared by all robots) are
  concatenated to ``h`` (the authors' public code drops the height-map embedding; here it is fused);
* ``n_layers - 1`` hidden ``hidden x hidden`` layers generated from the mean-pooled context;
* **output layer**: per limb generated weights (hidden -> 2 action slots) and bias.

Three context encoders (input, hidden, output layer), each ``Linear(C -> e)`` plus one pre-LN
Transformer layer over the limbs with the padding mask.

**Task input** (``task_input``): the paper trains one hypernetwork per task. With
``task_input="index"`` one student stands for them all: the one-hot of the ``task_index``
observation is appended to every limb's context, so the hypernetwork writes one MLP per
(robot, task) and can tell tasks whose observations are alike (FT and Incline share their
observation keys) apart. ``task_input="none"`` (the constructor's default, so students saved
before the option load and act as they did) gives no task to the student: it must guess the task
from the observations. The pipeline's default for new runs is ``"index"``
(``hyperdistill.task_input``).

**Observation normalisation** (``observation_statistics``): with ``"teachers"`` the student
normalises every state with the statistics of the teacher of that state's task (the paper: each
task's hypernetwork on its teacher's normaliser), held in the policy (per task index, set by
:meth:`HyperDistillPolicy.set_teacher_statistics`, saved in ``model.zip``); it then reads raw
observations (no ``VecNormalize`` of its own), sees for each task exactly the inputs its teacher
saw, and an exported MLP bakes its task's teacher's statistics in. With ``"own"`` (the
constructor's default: students saved before the option) the policy reads observations normalised
outside it, in the pipeline by one ``VecNormalize`` of the student's own (``proprioceptive``,
statistics over the states of all the training tasks, ``vecnormalize.pkl``). Every generator starts with a zero weight
matrix; the generated weights start ~N(0, 1/fan_in) (the generator's bias), generated biases at 0.

Training is distillation from a teacher (ModuMorph by default, any teacher of the pipeline):
offline from teacher rollouts (:mod:`sb3_divmorph.algos.hyperdistill_fit`) and/or DAgger
(:class:`~sb3_divmorph.algos.distillation.DAggerCallback` with
:class:`~sb3_divmorph.algos.distillation.ImitationPPO`). Deployment: for one robot the MLP is
generated once (:class:`~sb3_divmorph.deploy.hyperdistill_mlp.HyperDistillMLP`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.preprocessing import preprocess_obs
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from sb3_divmorph.nn.distributions import MaskedDiagGaussianDistribution
from sb3_divmorph.nn.extractors import ACT_PADDING_MASK, CONTEXT, OBS_PADDING_MASK, PROPRIOCEPTIVE, ExteroceptionEncoder, token_padding
from sb3_divmorph.nn.gates import masked_mean
from sb3_divmorph.nn.layers import LinearBuilder
from sb3_divmorph.nn.transformer import TransformerEncoderLayer, attention_mask
from sb3_divmorph.policies.modumorph import RobotBatch

#: Sizes per preset: ``paper`` is the authors' reported setting (2 layers of width 256,
#: context encoders of width 128 with a 2-head Transformer layer of FFN 256).
HYPERDISTILL_PRESETS: dict[str, dict[str, Any]] = {
    "small": dict(
        hidden_dim=64, n_layers=2, embed_dim=32, n_heads=2, encoder_ff_dim=64, exteroception=dict(hfield=[32, 32], goal=[16], object=[16])
    ),
    "paper": dict(
        hidden_dim=256,
        n_layers=2,
        embed_dim=128,
        n_heads=2,
        encoder_ff_dim=256,
        exteroception=dict(hfield=[64, 64], goal=[32], object=[32]),
    ),
}
LOSSES = ("nll", "kl")
#: What the student is told of the task: nothing, or the one-hot of ``task_index``.
TASK_INPUTS = ("none", "index")
TASK_INDEX = "task_index"
#: Whose observation statistics the student uses: its own (normalised outside it) or its teachers'.
OBSERVATION_STATISTICS = ("own", "teachers")


class LimbContextEncoder(nn.Module):
    """``Linear(C -> e)`` then one pre-LN Transformer layer over the limbs (padding masked).

    :param context_dim: per-token context features.
    :param embed_dim: output width.
    :param n_heads: attention heads.
    :param ff_dim: FFN width.
    """

    def __init__(self, context_dim: int, embed_dim: int, n_heads: int, ff_dim: int):
        super().__init__()
        self.linear = nn.Linear(context_dim, embed_dim)
        self.layer = TransformerEncoderLayer(embed_dim, n_heads, ff_dim, LinearBuilder())

    def forward(self, context: th.Tensor, padding: th.Tensor) -> th.Tensor:
        return self.layer(self.linear(context), attention_mask(padding))


def _generator(embed_dim: int, numel: int, std: float) -> nn.Linear:
    layer = nn.Linear(embed_dim, numel)
    nn.init.zeros_(layer.weight)
    nn.init.normal_(layer.bias, 0.0, std) if std > 0 else nn.init.zeros_(layer.bias)
    return layer


class MLPWeights(NamedTuple):
    """The generated MLP of U robots (padded limbs contribute zero rows / columns).

    ``w_in`` (U, L*P, H), ``b_in`` (U, H), ``hidden`` [(U, in, out), (U, out)] per hidden layer,
    ``w_out`` (U, in, L*S), ``b_out`` (U, L*S).
    """

    w_in: th.Tensor
    b_in: th.Tensor
    hidden: list[tuple[th.Tensor, th.Tensor]]
    w_out: th.Tensor
    b_out: th.Tensor

    def per_robot(self) -> list[MLPWeights]:
        """The U robots' MLPs, one each (the leading U dimension dropped).

        Split by ``unbind``, whose backward stacks the robots' gradients once; indexing robot by robot
        would make every index's backward allocate a gradient of the whole (U, ...) tensor, quadratic in
        U (a batch of hundreds of robot x task pairs then spends its time zero-filling).
        """
        hidden = [list(zip(w.unbind(0), b.unbind(0))) for w, b in self.hidden]
        parts = zip(self.w_in.unbind(0), self.b_in.unbind(0), self.w_out.unbind(0), self.b_out.unbind(0))
        return [MLPWeights(w_in, b_in, [layer[u] for layer in hidden], w_out, b_out) for u, (w_in, b_in, w_out, b_out) in enumerate(parts)]


class HyperDistillNetwork(nn.Module):
    """The HN-MLP student: context -> MLP weights, and the MLP run on the robot's observations.

    :param observation_space: the UNIMAL ``spaces.Dict``.
    :param slots_per_token: action slots per token (2).
    :param hidden_dim: MLP width.
    :param n_layers: MLP layers before the output layer (input layer + ``n_layers - 1`` hidden).
    :param embed_dim: width of the three context encoders.
    :param n_heads: heads of their Transformer layer.
    :param encoder_ff_dim: FFN width of their Transformer layer.
    :param exteroception: ``{obs key: MLP widths}`` of the fused global encoders.
    :param task_input: ``"none"`` (no task input) or ``"index"`` (the one-hot of ``task_index``
        appended to every limb's context: the generated MLP depends on the robot and the task).
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        slots_per_token: int,
        hidden_dim: int,
        n_layers: int,
        embed_dim: int,
        n_heads: int,
        encoder_ff_dim: int,
        exteroception: Mapping[str, Sequence[int]] | None,
        task_input: str = "none",
    ):
        super().__init__()
        if n_layers < 1:
            raise ValueError(f"n_layers must be >= 1, got {n_layers}")
        if task_input not in TASK_INPUTS:
            raise ValueError(f"task_input must be one of {list(TASK_INPUTS)}, got {task_input!r}")
        self.n_tokens, self.proprio_dim = observation_space[PROPRIOCEPTIVE].shape
        self.task_input, self.n_tasks = task_input, 0
        if task_input == "index":
            if TASK_INDEX not in observation_space.spaces:
                raise ValueError(
                    f"task_input='index' needs a {TASK_INDEX!r} observation; the observation space has {sorted(observation_space.spaces)}"
                )
            self.n_tasks = int(observation_space[TASK_INDEX].high.max()) + 1
        self.context_dim = observation_space[CONTEXT].shape[1] + self.n_tasks
        self.slots, self.hidden_dim, self.embed_dim = slots_per_token, hidden_dim, embed_dim
        extero = {k: list(v) for k, v in sorted((exteroception or {}).items()) if k in observation_space.spaces and len(v) > 0}
        self.exteroception = nn.ModuleDict(
            {k: ExteroceptionEncoder(int(np.prod(observation_space[k].shape)), dims) for k, dims in extero.items()}
        )
        extero_dim = sum(e.out_dim for e in self.exteroception.values())
        self.encoders = nn.ModuleList(LimbContextEncoder(self.context_dim, embed_dim, n_heads, encoder_ff_dim) for _ in range(3))
        P, H, S = self.proprio_dim, hidden_dim, slots_per_token
        self.in_weight = _generator(embed_dim, P * H, 1 / math.sqrt(P))
        self.in_bias = _generator(embed_dim, H, 0.0)
        sizes = [H + extero_dim] + [H] * (n_layers - 1)  # inputs of every layer after the input layer
        self.hidden_sizes = list(zip(sizes[:-1], sizes[1:]))
        self.hidden_weight = nn.ModuleList(_generator(embed_dim, a * b, 1 / math.sqrt(a)) for a, b in self.hidden_sizes)
        self.hidden_bias = nn.ModuleList(_generator(embed_dim, b, 0.0) for _, b in self.hidden_sizes)
        self.out_in = sizes[-1]
        self.out_weight = _generator(embed_dim, self.out_in * S, 1 / math.sqrt(self.out_in))
        self.out_bias = _generator(embed_dim, S, 0.0)

    def check_tokens(self, tokens: int, what: str = "robot") -> None:
        if tokens > self.n_tokens:
            raise ValueError(f"{what} has {tokens} tokens (torso + limbs); this HyperDistill student supports at most {self.n_tokens}")
        if tokens != self.n_tokens:
            raise ValueError(f"{what} has {tokens} token rows; pad it to the student's {self.n_tokens} (obs_padding_mask)")

    def context_input(self, observations: Mapping[str, th.Tensor], padding: th.Tensor) -> th.Tensor:
        """(B, L, C [+ n_tasks]) what the context encoders read: the context (padded rows zeroed),
        with the task's one-hot on every real limb when ``task_input == "index"``."""
        context = observations[CONTEXT]
        if self.n_tasks:
            index = observations[TASK_INDEX].reshape(len(context)).round().long()
            if bool(((index < 0) | (index >= self.n_tasks)).any()):
                raise ValueError(f"task_index {index.tolist()} outside the student's {self.n_tasks} tasks")
            one_hot = nn.functional.one_hot(index, self.n_tasks).to(context.dtype)
            context = th.cat([context, one_hot[:, None].expand(-1, context.shape[1], -1)], dim=-1)
        return th.where(padding[..., None], th.zeros((), dtype=context.dtype, device=context.device), context)

    def _encode(self, context: th.Tensor, padding: th.Tensor) -> th.Tensor:
        # one tensor per robot for RobotBatch: the three encodings and the real-limb mask
        encodings = [encoder(context, padding) for encoder in self.encoders]
        return th.cat([*encodings, (~padding).to(context.dtype)[..., None]], dim=-1)

    def generate(self, robot_encoding: th.Tensor) -> MLPWeights:
        """(U, L, 3e + 1) robot encodings -> the U robots' MLP weights."""
        e = self.embed_dim
        enc_in, enc_hidden, enc_out = (robot_encoding[..., i * e : (i + 1) * e] for i in range(3))
        real = robot_encoding[..., -1:]  # (U, L, 1)
        U, L = robot_encoding.shape[:2]
        P, H, S = self.proprio_dim, self.hidden_dim, self.slots
        w_in = (self.in_weight(enc_in).view(U, L, P, H) * real[..., None]).reshape(U, L * P, H)
        b_in = (self.in_bias(enc_in) * real).sum(1)
        pooled = masked_mean(enc_hidden, real[..., 0] < 0.5)
        hidden = [(wg(pooled).view(U, a, b), bg(pooled)) for (a, b), wg, bg in zip(self.hidden_sizes, self.hidden_weight, self.hidden_bias)]
        w_out = self.out_weight(enc_out).view(U, L, self.out_in, S) * real[..., None]
        w_out = w_out.permute(0, 2, 1, 3).reshape(U, self.out_in, L * S)
        b_out = (self.out_bias(enc_out) * real).reshape(U, L * S)
        return MLPWeights(w_in, b_in, hidden, w_out, b_out)

    def encode_extero(self, observations: Mapping[str, th.Tensor]) -> th.Tensor | None:
        if not len(self.exteroception):
            return None
        return th.cat([enc(observations[k].flatten(1)) for k, enc in self.exteroception.items()], dim=-1)

    def real_indices(self, real_tokens: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Rows of the flat proprioception and columns of the flat action of the given real tokens."""
        rows = (real_tokens[:, None] * self.proprio_dim + th.arange(self.proprio_dim, device=real_tokens.device)).flatten()
        cols = (real_tokens[:, None] * self.slots + th.arange(self.slots, device=real_tokens.device)).flatten()
        return rows, cols

    @staticmethod
    def run_mlp(weights: MLPWeights, proprio: th.Tensor, extero: th.Tensor | None, rows: th.Tensor, cols: th.Tensor) -> th.Tensor:
        """One robot's MLP (``weights`` of :meth:`MLPWeights.per_robot`) on its real limbs: (n, L*P) flat
        proprioception (+ (n, E)) -> (n, len(cols)).

        Only the real limbs' rows and columns are multiplied, exactly as in the deployed
        :class:`HyperDistillMLP` (same operations in the same order, so both agree to float rounding).
        """
        h = th.relu(proprio[:, rows] @ weights.w_in[rows] + weights.b_in)
        if extero is not None:
            h = th.cat([h, extero], dim=-1)
        for w, b in weights.hidden:
            h = th.relu(h @ w + b)
        return h @ weights.w_out[:, cols] + weights.b_out[cols]

    def forward(self, observations: Mapping[str, th.Tensor]) -> th.Tensor:
        """(B, L * slots) action means (0 on padded tokens' slots) from a preprocessed observation dict."""
        proprio = observations[PROPRIOCEPTIVE]
        self.check_tokens(proprio.shape[1])
        self.check_tokens(observations[CONTEXT].shape[1], "context")
        padding = token_padding(observations)
        zero = th.zeros((), dtype=proprio.dtype, device=proprio.device)
        proprio = th.where(padding[..., None], zero, proprio).flatten(1)  # NaN-safe: padded rows never read
        context = self.context_input(observations, padding)  # one group per (robot, task) with a task input
        robots = RobotBatch.from_context(context, self._encode, padding)
        weights = self.generate(robots.embedding).per_robot()
        extero = self.encode_extero(observations)
        groups = proprio[robots.order].split(robots.counts)
        extero_groups = extero[robots.order].split(robots.counts) if extero is not None else [None] * len(groups)
        out = proprio.new_zeros(len(proprio), self.n_tokens * self.slots)
        start = 0
        for u, (p, x) in enumerate(zip(groups, extero_groups)):
            rows, cols = self.real_indices(th.nonzero(robots.embedding[u, :, -1] > 0.5).flatten())
            samples = robots.order[start : start + len(p)]
            out[samples[:, None], cols[None, :]] = self.run_mlp(weights[u], p, x, rows, cols)
            start += len(p)
        return out


class HyperDistillPolicy(ActorCriticPolicy):
    """The HyperDistill student as an SB3 policy (for :class:`~sb3_divmorph.algos.distillation.ImitationPPO`
    rollouts and :class:`~sb3_divmorph.algos.distillation.DAggerCallback`).

    Actor: :class:`HyperDistillNetwork`, masked Gaussian with a fixed std (``action_std``). The student
    is trained by imitation only, so its critic is a single learnable constant: SB3's rollout
    buffer needs values, nothing here learns from them.

    :param observation_space: the UNIMAL ``spaces.Dict``.
    :param action_space: ``Box(-1, 1, (L * slots,))``.
    :param lr_schedule: learning-rate schedule (SB3's optimiser; distillation uses its own).
    :param preset: ``"small"`` (default) or ``"paper"``; explicit keywords override it.
    :param hidden_dim: MLP width.
    :param n_layers: MLP layers before the output layer.
    :param embed_dim: context-encoder width.
    :param n_heads: context-encoder heads.
    :param encoder_ff_dim: context-encoder FFN width.
    :param exteroception: ``{obs key: MLP widths}``.
    :param action_std: std of the Gaussian (MetaMorph's teachers: 0.9).
    :param task_input: ``"none"`` (default: no task input, the students saved before this option) or
        ``"index"`` (the ``task_index`` one-hot conditions the hypernetwork, see :class:`HyperDistillNetwork`).
    :param observation_statistics: ``"own"`` (default: observations come normalised, e.g. by the
        student's ``VecNormalize``) or ``"teachers"`` (raw observations in; each normalised with the
        statistics of its task's teacher, see :meth:`set_teacher_statistics`).
    :param normalized_keys: the observations the teachers' statistics cover (``"teachers"`` only).
    :param kwargs: other ``ActorCriticPolicy`` arguments (optimizer).
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        preset: str = "small",
        hidden_dim: int | None = None,
        n_layers: int | None = None,
        embed_dim: int | None = None,
        n_heads: int | None = None,
        encoder_ff_dim: int | None = None,
        exteroception: Mapping[str, Sequence[int]] | None = None,
        action_std: float = 0.9,
        task_input: str = "none",
        observation_statistics: str = "own",
        normalized_keys: Sequence[str] = ("proprioceptive",),
        **kwargs: Any,
    ):
        if task_input not in TASK_INPUTS:
            raise ValueError(f"task_input must be one of {list(TASK_INPUTS)}, got {task_input!r}")
        if observation_statistics not in OBSERVATION_STATISTICS:
            raise ValueError(f"observation_statistics must be one of {list(OBSERVATION_STATISTICS)}, got {observation_statistics!r}")
        self.task_input, self.observation_statistics, self.normalized_keys = task_input, observation_statistics, tuple(normalized_keys)
        if preset not in HYPERDISTILL_PRESETS:
            raise ValueError(f"Unknown preset {preset!r}; choose from {sorted(HYPERDISTILL_PRESETS)}")
        explicit = dict(
            hidden_dim=hidden_dim,
            n_layers=n_layers,
            embed_dim=embed_dim,
            n_heads=n_heads,
            encoder_ff_dim=encoder_ff_dim,
            exteroception=exteroception,
        )
        self.preset = preset
        self.config = {**HYPERDISTILL_PRESETS[preset], **{k: v for k, v in explicit.items() if v is not None}}
        self.action_std = float(action_std)
        if not isinstance(observation_space, spaces.Dict) or not {PROPRIOCEPTIVE, CONTEXT, OBS_PADDING_MASK, ACT_PADDING_MASK} <= set(
            observation_space.spaces
        ):
            raise ValueError("HyperDistillPolicy needs the UNIMAL Dict observation space")
        n_tokens = observation_space[PROPRIOCEPTIVE].shape[0]
        if len(action_space.shape) != 1 or action_space.shape[0] % n_tokens:
            raise ValueError(f"Action size {action_space.shape} is not a multiple of the {n_tokens} tokens")
        self.n_tokens, self.slots_per_token = n_tokens, action_space.shape[0] // n_tokens
        for key in ("net_arch", "features_extractor_class", "share_features_extractor", "use_sde"):
            kwargs.pop(key, None)
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        for key in (
            "net_arch",
            "features_extractor_class",
            "features_extractor_kwargs",
            "share_features_extractor",
            "use_sde",
            "log_std_init",
            "squash_output",
            "full_std",
            "use_expln",
            "ortho_init",
            "activation_fn",
        ):
            data.pop(key, None)
        data.update(self.config, preset=self.preset, action_std=self.action_std)
        if self.task_input != "none":  # a student without a task input saves what it saved before
            data["task_input"] = self.task_input
        if self.observation_statistics != "own":
            data.update(observation_statistics=self.observation_statistics, normalized_keys=list(self.normalized_keys))
        return data

    def _build(self, lr_schedule: Schedule) -> None:
        self.action_dist = MaskedDiagGaussianDistribution(int(np.prod(self.action_space.shape)))
        self.network = HyperDistillNetwork(self.observation_space, self.slots_per_token, **self.config, task_input=self.task_input)
        self.value_constant = nn.Parameter(th.zeros(1))
        self.register_buffer("log_std", th.full((self.action_dist.action_dim,), math.log(self.action_std)))
        if self.observation_statistics == "teachers":
            if TASK_INDEX not in self.observation_space.spaces:
                raise ValueError(f"observation_statistics='teachers' needs a {TASK_INDEX!r} observation")
            n_tasks = int(self.observation_space[TASK_INDEX].high.max()) + 1
            for key in self.normalized_keys:
                shape = self.observation_space[key].shape
                self.register_buffer(f"teacher_mean_{key}", th.zeros((n_tasks, *shape), dtype=th.float64))
                self.register_buffer(f"teacher_var_{key}", th.ones((n_tasks, *shape), dtype=th.float64))
            self.register_buffer("teacher_epsilon", th.zeros(n_tasks, dtype=th.float64))
            self.register_buffer("teacher_clip", th.full((n_tasks,), math.inf, dtype=th.float64))
            self.register_buffer("teacher_set", th.zeros(n_tasks, dtype=th.bool))
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)  # type: ignore[call-arg]

    def set_teacher_statistics(self, task_index: int, normalizer: VecNormalize | None) -> None:
        """Normalise the states of task ``task_index`` as its teacher does (``observation_statistics="teachers"``).

        :param task_index: the task (``task_index`` observation).
        :param normalizer: the teacher's ``VecNormalize`` (its ``obs_rms``, ``epsilon``, ``clip_obs``),
            or ``None`` for a teacher trained on raw observations.
        :raises ValueError: the student does not use teachers' statistics, or the teacher normalises
            other observations than ``normalized_keys``.
        """
        if self.observation_statistics != "teachers":
            raise ValueError("set_teacher_statistics needs a student built with observation_statistics='teachers'")
        task_index = int(task_index)
        if normalizer is None:
            for key in self.normalized_keys:
                getattr(self, f"teacher_mean_{key}")[task_index] = 0.0
                getattr(self, f"teacher_var_{key}")[task_index] = 1.0
            self.teacher_epsilon[task_index], self.teacher_clip[task_index] = 0.0, math.inf
        else:
            teacher_keys = tuple(getattr(normalizer, "norm_obs_keys", None) or ()) if normalizer.norm_obs else ()
            if set(teacher_keys) != set(self.normalized_keys):
                raise ValueError(
                    f"the teacher of task {task_index} normalises {sorted(teacher_keys)}; this student "
                    f"holds statistics of {sorted(self.normalized_keys)} (normalized_keys)"
                )
            for key in self.normalized_keys:
                getattr(self, f"teacher_mean_{key}")[task_index] = th.as_tensor(normalizer.obs_rms[key].mean, dtype=th.float64)
                getattr(self, f"teacher_var_{key}")[task_index] = th.as_tensor(normalizer.obs_rms[key].var, dtype=th.float64)
            self.teacher_epsilon[task_index], self.teacher_clip[task_index] = float(normalizer.epsilon), float(normalizer.clip_obs)
        self.teacher_set[task_index] = True

    def normalize_with_teachers(self, obs: Mapping[str, th.Tensor]) -> dict[str, th.Tensor]:
        """Raw observations normalised with each state's task's teacher statistics (as ``VecNormalize``:
        float64 arithmetic, clipped, then float32)."""
        index = obs[TASK_INDEX].reshape(-1).round().long()
        missing = sorted({int(i) for i in index[~self.teacher_set[index]]})
        if missing:
            raise ValueError(
                f"no teacher statistics for task index(es) {missing}; this student holds them for "
                f"{th.nonzero(self.teacher_set).flatten().tolist()}"
            )
        out = dict(obs)
        clip = self.teacher_clip[index]
        for key in self.normalized_keys:
            mean, var = getattr(self, f"teacher_mean_{key}")[index], getattr(self, f"teacher_var_{key}")[index]
            eps = self.teacher_epsilon[index].view(-1, *[1] * (mean.dim() - 1))
            x = (obs[key].double() - mean) / th.sqrt(var + eps)
            c = clip.view_as(eps)
            out[key] = th.minimum(th.maximum(x, -c), c).to(obs[key].dtype)
        return out

    def task_normalizer(self, task_index: int) -> _TaskStatistics:
        """The teacher statistics of one task as a ``VecNormalize``-like object (for :class:`HyperDistillMLP`)."""
        task_index = int(task_index)
        if not bool(self.teacher_set[task_index]):
            raise ValueError(f"no teacher statistics for task index {task_index}")
        return _TaskStatistics(self, task_index)

    def _preprocess(self, obs: PyTorchObs) -> dict[str, th.Tensor]:
        obs = preprocess_obs(obs, self.observation_space, normalize_images=False)
        return self.normalize_with_teachers(obs) if self.observation_statistics == "teachers" else obs  # type: ignore[return-value,arg-type]

    def _distribution(self, obs: Mapping[str, th.Tensor]) -> MaskedDiagGaussianDistribution:
        return self.action_dist.proba_distribution(self.network(obs), self.log_std, obs[ACT_PADDING_MASK])

    def _values(self, obs: Mapping[str, th.Tensor]) -> th.Tensor:
        # a product, not a view: a view of a parameter keeps requires_grad even under no_grad
        return obs[PROPRIOCEPTIVE].new_ones(obs[PROPRIOCEPTIVE].shape[0], 1) * self.value_constant

    def forward(self, obs: PyTorchObs, deterministic: bool = False):
        obs = self._preprocess(obs)
        distribution = self._distribution(obs)
        actions = distribution.get_actions(deterministic=deterministic)
        return actions.reshape((-1, *self.action_space.shape)), self._values(obs), distribution.log_prob(actions)

    def evaluate_actions(self, obs: PyTorchObs, actions: th.Tensor):
        obs = self._preprocess(obs)
        distribution = self._distribution(obs)
        return self._values(obs), distribution.log_prob(actions), distribution.entropy()

    def get_distribution(self, obs: PyTorchObs):
        return self._distribution(self._preprocess(obs))

    def predict_values(self, obs: PyTorchObs) -> th.Tensor:
        return self._values(self._preprocess(obs))

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self.get_distribution(observation).get_actions(deterministic=deterministic)

    def parameter_counts(self) -> dict[str, int]:
        """Student parameters: context encoders, generators, exteroception encoders."""
        n = self.network

        def count(*modules: nn.Module) -> int:
            return sum(p.numel() for m in modules for p in m.parameters())

        return {
            "context_encoders": count(n.encoders),
            "generators": count(n.in_weight, n.in_bias, n.hidden_weight, n.hidden_bias, n.out_weight, n.out_bias),
            "exteroception": count(n.exteroception),
            "total": count(self),
        }


class _RunningStats(NamedTuple):
    mean: np.ndarray
    var: np.ndarray


class _TaskStatistics:
    """One task's teacher statistics of a student, read like a ``VecNormalize`` (``norm_obs_keys``,
    ``obs_rms``, ``epsilon``, ``clip_obs``, ``normalize_obs``)."""

    def __init__(self, policy: HyperDistillPolicy, task_index: int):
        self.norm_obs_keys = list(policy.normalized_keys)
        self.obs_rms = {
            k: _RunningStats(
                getattr(policy, f"teacher_mean_{k}")[task_index].cpu().numpy(),
                getattr(policy, f"teacher_var_{k}")[task_index].cpu().numpy(),
            )
            for k in self.norm_obs_keys
        }
        self.epsilon = float(policy.teacher_epsilon[task_index])
        self.clip_obs = float(policy.teacher_clip[task_index])

    def normalize_obs(self, obs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        out = {k: np.array(v) for k, v in obs.items()}
        for k in self.norm_obs_keys:
            x = (obs[k] - self.obs_rms[k].mean) / np.sqrt(self.obs_rms[k].var + self.epsilon)
            out[k] = np.clip(x, -self.clip_obs, self.clip_obs).astype(np.float32)
        return out
