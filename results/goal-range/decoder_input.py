"""How much of the actor decoder's first pre-activation comes from the goal input, raw and bounded? (issue 67 (b))

The actor decoder reads, per token, the Transformer's output and the exteroception encodings (the
goal's among them). Its first layer is linear (then gated per unit), so its pre-activation is the sum
of one contribution per part of its input: a part's contribution is the layer applied to that part
alone minus the layer applied to zeros. This prints the rms over robots, tokens and units of the
goal's and the tokens' contributions, for the DivMorph student (told Patrol's instruction, as in the
race) and MetaMorph⚗ (told PointNav's), on PointNav and Patrol reset states of the race's 20 curve
robots x 5 episodes, with raw goals and with ``goal_range=10``.

    python results/goal-range/decoder_input.py --run results/cpu100
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th

from divmorph.pipeline.curves import episode_seed
from divmorph.pipeline.folders import student_folder
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.robots import transfer_eval_robots
from divmorph.pipeline.transfer import _feature_layout
from divmorph.pretrained import load_pretrained
from unimal_envs.instructions import INSTRUCTIONS

HERE = Path(__file__).resolve().parent


def contributions(model, observations: list[dict]) -> dict[str, float]:
    """rms of each input part's contribution to the actor decoder's first pre-activation."""
    policy = model.model.policy
    captured = {}
    decoder = policy.mlp_extractor.policy_net
    handle = decoder.register_forward_hook(
        lambda module, inputs, output: captured.update(x=inputs[0], gates=inputs[1] if len(inputs) > 1 else None)
    )
    batch = {k: np.stack([o[k] for o in observations]) for k in observations[0]}
    if model.normalizer is not None:
        batch = model.normalizer.normalize_obs(batch)
    with th.no_grad():
        obs, _ = policy.obs_to_tensor(batch)
        policy.get_distribution(obs)
    handle.remove()
    x, gates = captured["x"], captured["gates"]
    layer = decoder.layers[0]
    real = obs["obs_padding_mask"] < 0.5
    found, start = {}, 0
    with th.no_grad():
        zero = layer(th.zeros_like(x), gates)
        for part, width in _feature_layout(policy):
            only = th.zeros_like(x)
            only[..., start : start + width] = x[..., start : start + width]
            found[part] = float((layer(only, gates) - zero)[real].pow(2).mean().sqrt())
            start += width
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, default=Path("results/cpu100"))
    parser.add_argument("--episodes", type=int, default=5)
    args = parser.parse_args()
    th.set_num_threads(1)
    robots = transfer_eval_robots(recorded_profile(args.run / "run.json"), "train")
    models = {"DivMorph student (told Patrol)": ("divmorph", "Patrol"), "MetaMorph⚗ (told the task's own)": ("distilled", None)}
    lines = [
        "| model | task | goal input | rms of the goal's contribution | rms of the tokens' contribution | goal / tokens |",
        "|---|---|---|---:|---:|---:|",
    ]
    for label, (student, told) in models.items():
        model = load_pretrained(student_folder(args.run, student))
        for task in ("Patrol", "PointNav"):
            instruction = INSTRUCTIONS[told or task]
            for goal_range in (None, 10.0):
                settings = {} if goal_range is None else {"goal_range": goal_range}
                observations = []
                for robot in robots:
                    env = gym.make(f"Unimal-{task}-v0", morphologies=[robot], instruction=instruction, **settings)
                    observations += [env.reset(seed=episode_seed(0, robot, e))[0] for e in range(args.episodes)]
                    env.close()
                parts = contributions(model, observations)
                lines.append(
                    f"| {label} | {task} | {'raw' if goal_range is None else f'goal_range {goal_range:g}'} | {parts['goal']:.1f} | "
                    f"{parts['tokens']:.1f} | {parts['goal'] / parts['tokens']:.1f} |"
                )
    lines.append(
        f"\nReset states of {len(robots)} curve robots x {args.episodes} episodes each; {time.strftime('%Y-%m-%d')}, 1 torch thread."
    )
    text = "\n".join(lines)
    (HERE / "decoder-input.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
