"""Make the saved models that ``tests/test_saved_models.py`` loads: tiny MetaMorph and DivMorph PPO models, saved
by the code of a past commit, with what they did then (deterministic actions and values on fixed observations).

Run with that commit's code on the path, e.g. the commit before issue 82 (the fused rollout pass, inference mode):

    git worktree add /tmp/old 75173f4
    PYTHONPATH=/tmp/old python tests/data/saved_before/make.py tests/data/saved_before 75173f4
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import PPO

from sb3_divmorph.testing import random_observations
from unimal_envs import contract

TINY = dict(d_model=16, n_layers=1, n_heads=2, ff_dim=32, net_arch=dict(pi=[16], vf=[16]), exteroception=dict(goal=[4]))
POLICIES = {
    "MetaMorphPolicy": TINY,
    "DivMorphPolicy": dict(TINY, n_morph_tailors=3, n_task_tailors=3, top_k_morph=2, top_k_task=2, morph_embed_dim=8, gate_hidden_dim=8),
}


class StandIn(gym.Env):
    """The contract's spaces and nothing else: PPO needs an env to be built."""

    observation_space = contract.observation_space()
    action_space = contract.action_space()

    def reset(self, *, seed=None, options=None):
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


def main(out: Path, commit: str) -> None:
    import sb3_divmorph

    print("code:", Path(sb3_divmorph.__file__).parent)
    out.mkdir(parents=True, exist_ok=True)
    observations = random_observations(contract.observation_space(), 6, seed=0, n_morphologies=3, n_tasks=2)
    expected: dict[str, np.ndarray] = {f"obs/{key}": value for key, value in observations.items()}
    for name, kwargs in POLICIES.items():
        th.manual_seed(0)
        model = PPO(name, StandIn(), policy_kwargs=kwargs, seed=0, device="cpu")
        with th.no_grad():  # move every weight off its init, so the test sees trained-looking values
            for p in model.policy.parameters():
                p.add_(0.1 * th.randn_like(p))
        model.save(out / f"{name}.zip")
        actions, _ = model.predict(observations, deterministic=True)
        obs_t, _ = model.policy.obs_to_tensor(observations)
        with th.no_grad():
            values = model.policy.predict_values(obs_t).numpy()
        expected[f"{name}/actions"], expected[f"{name}/values"] = actions, values
    np.savez_compressed(out / "expected.npz", **expected)
    (out / "made_by.json").write_text(json.dumps({"commit": commit, "torch": th.__version__}, indent=1) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2])
