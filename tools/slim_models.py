"""Slim the shipped SB3 models without changing what they do, and check that they do the same.

    python tools/slim_models.py                     # check only: what slimming would save, and that it is exact
    python tools/slim_models.py --write             # the same check, then re-save every shipped model in place
    python tools/slim_models.py --against <commit>  # compare the models as they are with those of an older commit

A ``model.zip`` as PPO saves it holds, besides the weights, Adam's moment estimates (twice the
parameters) and the last rollout observation (``_last_obs`` / ``_last_original_obs``); its
``vecnormalize.pkl`` holds the last observation too (``old_obs``). None of them is needed to act,
evaluate, distil, export or transfer: transfer and GRL copy the weights into a new PPO with a new
optimiser, and a finished run is never trained further (a new budget retrains the stage). Slimming
re-saves each model with:

* the optimiser's state emptied, its parameter groups kept (``PPO.load`` with its default
  ``exact_match`` loads it; training it again restarts Adam's moments from zero);
* without ``_last_obs`` and ``_last_original_obs`` (``learn`` resets the env when they are missing);
* deflate-compressed (``zipfile`` reads it as before);
* and the normaliser without ``old_obs`` (set again by the env's first ``reset``).

The check, before anything is written: every tensor of the policy is bit-identical, every other
saved attribute is equal, the normaliser's statistics are bit-identical, and the deterministic
actions and the unclipped action means on the same observations (8 seeded steps of each of the five training tasks on the shipped
``train`` robots, normalised by the model's own statistics) are bit-identical.
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import pickle
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecNormalize

import sb3_divmorph  # noqa: F401  (the policies PPO.load unpickles)
import unimal_envs  # noqa: F401  (registers the envs)
from unimal_envs import env_id

ROOT = Path(__file__).resolve().parents[1]


def shipped() -> list[str]:
    """The folders of the models a fresh clone ships (``git ls-files 'results/*model.zip'``)."""
    listed = subprocess.run(["git", "ls-files", "results/*model.zip"], cwd=ROOT, check=True, capture_output=True, text=True).stdout
    return sorted(str(Path(line).parent) for line in listed.splitlines())


TASKS = ("FT", "VT", "Incline", "Obstacle", "Patrol")
#: attributes of a saved PPO that slimming leaves out
DROPPED = ("_last_obs", "_last_original_obs")
STEPS = 8


def observations() -> dict[str, dict[str, np.ndarray]]:
    """``STEPS`` raw observations of each training task (seeded random actions, shipped robots)."""
    batches = {}
    for task in TASKS:
        env = gym.make(env_id(task))
        env.action_space.seed(0)
        obs, _ = env.reset(seed=0)
        rows = [obs]
        while len(rows) < STEPS:
            obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                obs, _ = env.reset()
            rows.append(obs)
        env.close()
        batches[task] = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
    return batches


def slim_model(data: bytes) -> bytes:
    """``model.zip`` bytes re-saved with an empty optimiser state, without ``DROPPED``, deflated."""
    model = PPO.load(io.BytesIO(data), device="cpu")
    model.policy.optimizer.state.clear()
    saved = io.BytesIO()
    model.save(saved, exclude=list(DROPPED))
    out = io.BytesIO()
    with zipfile.ZipFile(saved) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as target:
        for name in source.namelist():
            target.writestr(name, source.read(name))
    return out.getvalue()


def slim_normalizer(data: bytes) -> bytes:
    normalizer = pickle.loads(data)
    normalizer.old_obs = None
    # what VecNormalize.__getstate__ leaves out (an unpickled normaliser has no env yet)
    normalizer.venv, normalizer.class_attributes, normalizer.returns = None, {}, None
    return pickle.dumps(normalizer)


def _saved_attributes(data: bytes) -> dict:
    """The ``data`` entry of a saved model: each attribute SB3 pickled as its pickle (a class by its
    module and name), the rest as saved. SB3 writes a readable summary beside each pickle -- a class's
    docstring, memory addresses -- which changes with the code, not with the model."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        saved = json.loads(archive.read("data").decode())
    return {
        key: _pickled(value[":serialized:"]) if isinstance(value, dict) and ":serialized:" in value else value
        for key, value in saved.items()
    }


def _pickled(serialized: str) -> object:
    """A pickled class as the class it loads (one class pickles under another module path once its
    home moved: ``sb3_divmorph.policies.MetaMorphPolicy`` then, ``...policies.morphology_transformer``
    now); any other pickle as its bytes."""
    raw = base64.b64decode(serialized)
    try:
        loaded = pickle.loads(raw)
    except Exception:  # noqa: BLE001 -- a pickle this environment cannot load: compare its bytes
        return raw
    return loaded if isinstance(loaded, type) else raw


def _statistics(normalizer: VecNormalize) -> dict[str, np.ndarray]:
    rms = normalizer.obs_rms if isinstance(normalizer.obs_rms, dict) else {"": normalizer.obs_rms}
    out = {f"obs/{k}/{name}": np.asarray(getattr(r, name)) for k, r in rms.items() for name in ("mean", "var", "count")}
    out.update({f"ret/{name}": np.asarray(getattr(normalizer.ret_rms, name)) for name in ("mean", "var", "count")})
    return out


def actions(model_data: bytes, normalizer: VecNormalize | None, batches: dict) -> tuple[PPO, np.ndarray]:
    """The model, and its deterministic actions beside its unclipped action means on ``batches``
    (normalised by ``normalizer``; ``None``: a model that normalises inside its policy, as HyperDistill's)."""
    model = PPO.load(io.BytesIO(model_data), device="cpu")
    if normalizer is not None:
        normalizer.training = False
    rows = []
    for batch in batches.values():
        normalized = batch if normalizer is None else normalizer.normalize_obs(batch)
        with th.no_grad():
            means = model.policy.get_distribution(model.policy.obs_to_tensor(normalized)[0]).distribution.mean.numpy()
        rows.append(np.concatenate([model.predict(normalized, deterministic=True)[0], means], axis=1))
    return model, np.concatenate(rows)


def compare(old_model: bytes, old_norm: bytes | None, new_model: bytes, new_norm: bytes | None, batches: dict) -> list[str]:
    """The differences between two versions of a model (empty: they are the same model); a model
    without a ``vecnormalize.pkl`` has ``None`` for its normaliser."""
    problems = []
    old_n = None if old_norm is None else pickle.loads(old_norm)
    new_n = None if new_norm is None else pickle.loads(new_norm)
    if (old_n is None) != (new_n is None):
        problems.append("one version has a normaliser, the other none")
    elif old_n is not None and new_n is not None:
        old_stats, new_stats = _statistics(old_n), _statistics(new_n)
        if old_stats.keys() != new_stats.keys() or not all(np.array_equal(old_stats[k], new_stats[k]) for k in old_stats):
            problems.append("normaliser statistics differ")
        for name in ("clip_obs", "clip_reward", "epsilon", "gamma", "norm_obs", "norm_reward", "norm_obs_keys"):
            if getattr(old_n, name) != getattr(new_n, name):
                problems.append(f"normaliser {name} differs")
    old, old_actions = actions(old_model, old_n, batches)
    new, new_actions = actions(new_model, None if new_norm is None else pickle.loads(new_norm), batches)
    if type(old.policy) is not type(new.policy):
        problems.append(f"policy class {type(old.policy).__name__} -> {type(new.policy).__name__}")
    a, b = old.policy.state_dict(), new.policy.state_dict()
    if a.keys() != b.keys() or not all(a[k].dtype == b[k].dtype and th.equal(a[k], b[k]) for k in a):
        problems.append("policy weights differ")
    groups = lambda m: [{k: v for k, v in g.items() if k != "params"} for g in m.policy.optimizer.state_dict()["param_groups"]]  # noqa: E731
    if groups(old) != groups(new):
        problems.append("optimiser parameter groups differ")
    old_attrs, new_attrs = _saved_attributes(old_model), _saved_attributes(new_model)
    for key in old_attrs.keys() | new_attrs.keys():
        if key not in DROPPED and old_attrs.get(key) != new_attrs.get(key):
            problems.append(f"saved attribute {key} differs")
    if old_actions.dtype != new_actions.dtype or not np.array_equal(old_actions, new_actions):
        problems.append(f"deterministic actions or action means differ (max |diff| {np.abs(old_actions - new_actions).max():.3g})")
    return problems


def _sizes(old: bytes | None, new: bytes | None) -> str:
    return "none" if old is None or new is None else f"{len(old):,} -> {len(new):,} B"


def at_commit(commit: str, path: str) -> bytes:
    return subprocess.run(["git", "show", f"{commit}:{path}"], cwd=ROOT, check=True, capture_output=True).stdout


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folders", nargs="*", help="model folders (default: every shipped one)")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--write", action="store_true", help="re-save the models in place once all of them pass the check")
    group.add_argument("--against", metavar="COMMIT", help="compare the models as they are with those at COMMIT")
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    folders = args.folders or shipped()
    batches = observations()
    print(f"{sum(len(b['proprioceptive']) for b in batches.values())} observations ({STEPS} per task of {', '.join(TASKS)})\n")
    print("| model | model.zip | vecnormalize.pkl | weights | deterministic actions |")
    print("|---|---|---|---|---|")
    failed, pending = [], []
    for folder in folders:
        model_path, norm_path = ROOT / folder / "model.zip", ROOT / folder / "vecnormalize.pkl"
        has_norm = norm_path.is_file()  # HyperDistill's student holds its teachers' statistics: no file
        if args.against:
            old_model = at_commit(args.against, f"{folder}/model.zip")
            old_norm = at_commit(args.against, f"{folder}/vecnormalize.pkl") if has_norm else None
            new_model, new_norm = model_path.read_bytes(), norm_path.read_bytes() if has_norm else None
        else:
            old_model, old_norm = model_path.read_bytes(), norm_path.read_bytes() if has_norm else None
            new_model, new_norm = slim_model(old_model), None if old_norm is None else slim_normalizer(old_norm)
        problems = compare(old_model, old_norm, new_model, new_norm, batches)
        n = sum(len(b["proprioceptive"]) for b in batches.values())
        print(
            f"| `{folder}` | {len(old_model):,} -> {len(new_model):,} B | {_sizes(old_norm, new_norm)} | "
            f"{'bit-identical' if not problems else 'DIFFERENT'} | "
            f"{'bit-identical on ' + str(n) if not problems else '; '.join(problems)} |"
        )
        (failed if problems else pending).append((folder, new_model, new_norm))
    if failed:
        print(f"\n{len(failed)} model(s) differ: {[f for f, _, _ in failed]}; nothing written", file=sys.stderr)
        return 1
    if args.write:
        for folder, new_model, new_norm in pending:
            for name, data in (("model.zip", new_model), ("vecnormalize.pkl", new_norm)):
                if data is None:
                    continue
                target = ROOT / folder / name
                with tempfile.NamedTemporaryFile(dir=target.parent, delete=False) as tmp:
                    tmp.write(data)
                Path(tmp.name).chmod(target.stat().st_mode & 0o777)
                Path(tmp.name).replace(target)
        print(f"\nre-saved {len(pending)} models in place")
    return 0


if __name__ == "__main__":
    sys.exit(main())
