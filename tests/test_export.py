"""Deployment: pruned compact actors of deployment diversions, like-for-like sizes, ONNX without torch."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import sb3_divmorph  # noqa: F401
import unimal_envs
from sb3_divmorph.deploy.compact import CompactActor, actor_inputs, export_onnx, size_comparison
from sb3_divmorph.nn.layers import FactorizedLinear
from unimal_envs.morphology.loader import morphology_files
from unimal_envs.tasks import TASKS

TINY = dict(d_model=16, n_layers=1, ff_dim=32, exteroception=dict(hfield=[8, 8], goal=[4], object=[4]))
ROBOTS = morphology_files("train")[:2]
ONNX_ACTOR = Path(sb3_divmorph.__file__).parent / "deploy" / "onnx_actor.py"


def trained_student(task: str, policy: str = "DivMorphPolicy", **policy_kwargs):
    """A tiny student moved off its init by a few PPO steps, its normaliser and a batch of raw observations."""
    th.manual_seed(2)
    venv = VecNormalize(
        DummyVecEnv([lambda: gym.make(unimal_envs.env_id(task), morphologies=ROBOTS[:1], max_episode_steps=50)]),
        norm_obs_keys=["proprioceptive", "hfield"],
    )
    model = PPO(policy, venv, n_steps=64, batch_size=64, n_epochs=1, seed=0, policy_kwargs={**TINY, **policy_kwargs})
    model.learn(64)
    venv.training = False
    venv.reset()
    raw = [venv.get_original_obs()]
    for _ in range(5):
        venv.step(np.random.uniform(-1, 1, (1, 24)).astype(np.float32))
        raw.append(venv.get_original_obs())
    batch = {k: np.concatenate([r[k] for r in raw]) for k in raw[0]}
    return model, venv, batch


def student_means(model, venv, batch) -> th.Tensor:
    obs_t, _ = model.policy.obs_to_tensor(venv.normalize_obs(batch))
    with th.no_grad():
        return model.policy.get_distribution(obs_t).distribution.mean


@pytest.mark.parametrize("task", ["VT", "ManipulateBox"])
def test_a_deployment_diversion_prunes_the_exteroception_encoders_too(task):
    model, venv, batch = trained_student(task, diversion="deploy-g2k1")
    extractor = model.policy.pi_features_extractor
    encoders = [m for m in extractor.exteroception.modules() if isinstance(m, FactorizedLinear)]
    assert encoders and all(m.n_tailors > 0 for m in encoders), "exteroception encoders are not diverted"
    # two learngenes everywhere; top-1 per gate keeps at most 2 + 1 + 1 units of any layer
    assert all(m.n_learngenes == 2 for m in extractor.encoder.modules() if isinstance(m, FactorizedLinear))
    first = {k: v[0] for k, v in batch.items()}
    actor = CompactActor.from_policy(model.policy, first, TASKS[task].observation_keys, venv)
    got = actor(*actor_inputs(batch, batch=True))
    assert (student_means(model, venv, batch) - got).abs().max().item() <= 1e-5
    for encoder in actor.exteroception.values():
        for layer in encoder:
            if hasattr(layer, "A"):
                assert layer.A.shape[1] <= 4
    # a deployed actor is not trained: no autograd graph, numpy conversion without torch.no_grad()
    assert not got.requires_grad and isinstance(got.numpy(), np.ndarray)


def test_a_metamorph_actor_exported_against_itself_is_one_times_smaller():
    model, venv, batch = trained_student("VT", policy="MetaMorphPolicy")
    first = {k: v[0] for k, v in batch.items()}
    actor = CompactActor.from_policy(model.policy, first, TASKS["VT"].observation_keys, venv)
    sizes = size_comparison(model.policy, actor, first, TASKS["VT"].observation_keys, venv)
    assert sizes["reduction"] == 1.0
    assert sizes["folding"] > 1.0  # folding alone shrinks it, and is reported apart


def test_like_for_like_reduction_does_not_credit_folding_to_pruning():
    model, venv, batch = trained_student("FT", n_morph_tailors=4, n_task_tailors=4, top_k_morph=2, top_k_task=2)
    first = {k: v[0] for k, v in batch.items()}
    actor = CompactActor.from_policy(model.policy, first, TASKS["FT"].observation_keys, venv)
    sizes = size_comparison(model.policy, actor, first, TASKS["FT"].observation_keys, venv)
    # FT lacks every exteroceptive input: folding removes those encoders from both sides alike
    assert sizes["metamorph_folded"] < sizes["metamorph_actor"]
    assert sizes["reduction"] == pytest.approx(sizes["metamorph_folded"] / actor.stored_numbers()["weights"])
    assert sizes["reduction"] < sizes["metamorph_actor"] / actor.stored_numbers()["weights"]


BLOCK_TORCH = textwrap.dedent(
    """
    import importlib.abc, importlib.util, json, sys
    import numpy as np

    class Blocker(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name.split(".")[0] in ("torch", "sb3_divmorph", "stable_baselines3", "unimal_envs"):
                raise ImportError(f"{name} is blocked in this test")

    sys.meta_path.insert(0, Blocker())
    spec = importlib.util.spec_from_file_location("onnx_actor", sys.argv[1])
    onnx_actor = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(onnx_actor)
    """
)


def test_onnx_actor_runs_with_onnxruntime_and_numpy_only(tmp_path):
    model, venv, batch = trained_student("VT", diversion="deploy-g2k1")
    first = {k: v[0] for k, v in batch.items()}
    actor = CompactActor.from_policy(model.policy, first, TASKS["VT"].observation_keys, venv)
    path = export_onnx(actor, first, tmp_path / "actor.onnx", {"robot": ROBOTS[0].stem, "task": "VT"})
    other = gym.make("Unimal-VT-v0", morphologies=[morphology_files("train")[5]]).reset(seed=0)[0]
    assert not np.array_equal(other["obs_padding_mask"], first["obs_padding_mask"])
    np.savez(tmp_path / "obs.npz", reference=student_means(model, venv, batch).numpy(), **batch)
    np.savez(tmp_path / "other.npz", **other)
    script = BLOCK_TORCH + textwrap.dedent(
        """
        d = dict(np.load(sys.argv[2])); other = dict(np.load(sys.argv[3]))
        actor = onnx_actor.OnnxActor(sys.argv[4])
        batch = actor({k: v for k, v in d.items() if k != "reference"})
        single = actor({k: v[0] for k, v in d.items() if k != "reference"})
        errors = []
        for bad in ({"proprioceptive": d["proprioceptive"][0, :, :10], "hfield": d["hfield"][0]},
                    {"hfield": d["hfield"][0]}, other):
            try:
                actor(bad)
            except onnx_actor.ObservationMismatchError as error:
                errors.append(str(error))
        assert "torch" not in sys.modules
        print(json.dumps({"diff": float(np.abs(batch - d["reference"]).max()), "single": float(np.abs(single - batch[0]).max()),
                          "meta": actor.metadata, "inputs": actor.input_shapes, "errors": errors}))
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", script, str(ONNX_ACTOR), str(tmp_path / "obs.npz"), str(tmp_path / "other.npz"), str(path)],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout)
    assert out["diff"] <= 1e-5 and out["single"] <= 1e-6
    assert out["meta"]["robot"] == ROBOTS[0].stem and out["meta"]["task"] == "VT"
    assert out["inputs"] == {"proprioceptive": [12, 52], "hfield": [1410]}
    assert len(out["errors"]) == 3
    assert "'proprioceptive' has shape (12, 10)" in out["errors"][0]
    assert "no 'proprioceptive'" in out["errors"][1]
    assert "exported for" in out["errors"][2] and ROBOTS[0].stem in out["errors"][2]


def test_baked_normalisation_keeps_float64_precision_for_nearly_constant_features():
    """A feature seen nearly constant has a huge inverse std: float32 statistics amplified the rounding
    of (x - mean) in trained students' exports (4e-5 off); the actor normalises in float64 like VecNormalize."""
    model, venv, batch = trained_student("FT", n_morph_tailors=4, n_task_tailors=4, top_k_morph=2, top_k_task=2)
    rms = venv.obs_rms["proprioceptive"]
    rms.mean[..., 0], rms.var[..., 0] = 100.0 + 3.3e-6, 1e-6  # nearly constant, far from zero, not a float32
    batch["proprioceptive"][..., 0] = np.float32(100.0) + np.float32(1e-4) * np.arange(len(batch["proprioceptive"]))[:, None]
    first = {k: v[0] for k, v in batch.items()}
    actor = CompactActor.from_policy(model.policy, first, TASKS["FT"].observation_keys, venv)
    with th.no_grad():
        diff = (student_means(model, venv, batch) - actor(*actor_inputs(batch, batch=True))).abs().max().item()
    assert diff <= 1e-5


def test_a_students_trained_adapters_are_kept_in_its_compact_actor():
    """A student fine-tuned by the ``adapter`` recipe exports with its adapters as extra always-on units:
    the compact actor acts as the student does (break: drop the adapter from ``selected_units`` -> the
    actions differ by the adapters' share)."""
    model, venv, batch = trained_student("VT", diversion="deploy-g2k1", adapter_rank=2)
    with th.no_grad():
        for layer in model.policy.modules():
            if isinstance(layer, FactorizedLinear) and layer.adapter_rank:
                layer.adapter_up.normal_(0, 0.3)  # as if trained: the adapters now change the function
    first = {k: v[0] for k, v in batch.items()}
    actor = CompactActor.from_policy(model.policy, first, TASKS["VT"].observation_keys, venv)
    assert (student_means(model, venv, batch) - actor(*actor_inputs(batch, batch=True))).abs().max().item() <= 1e-5
