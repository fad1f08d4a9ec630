"""The observation and action contract shared by every UNIMAL environment and policy.

Every task and every morphology exposes *exactly* the same spaces, so that one policy and one
vectorised env can mix tasks and morphologies freely. Policies in :mod:`sb3_divmorph` read the
key names and sizes from here rather than hard-coding them.

=====================  ==========  ===============================================================
key                    shape       meaning
=====================  ==========  ===============================================================
``proprioceptive``     (12, 52)    per-token features (torso first, then limbs in MuJoCo body order)
``context``            (12, 35)    static per-token morphology features rescaled to [-1, 1]
``obs_padding_mask``   (12,)       1.0 = padded token (MetaMorph convention)
``act_padding_mask``   (24,)       1.0 = padded action slot (no hinge there)
``hfield``             (1410,)     egocentric height map (47 x 30), zeros where the task has none
``goal``               (3,)        goal in the torso frame, zeros where the task has none
``object``             (12,)       object state in the torso frame, zeros where the task has none
``task_embedding``     (384,)      sentence embedding of the task instruction
``task_index``         (1,)        integer id of the task (:data:`TASK_NAMES` order) as float32
=====================  ==========  ===============================================================
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

#: Tokens per robot: torso + at most 11 limbs (MetaMorph's MAX_LIMBS = max(num_limbs) + 2).
MAX_TOKENS = 12
#: Hinge slots per token: slot 0 is the limb's "x" hinge, slot 1 its "y" hinge.
SLOTS_PER_TOKEN = 2
ACTION_DIM = MAX_TOKENS * SLOTS_PER_TOKEN
#: Per-token proprioceptive features (spec table 3.1).
PROPRIO_DIM = 52
#: Per-token context: 17 limb features + 2 x 9 hinge features (ModuMorph's context).
CONTEXT_DIM = 35
HFIELD_ROWS, HFIELD_COLS = 47, 30
HFIELD_DIM = HFIELD_ROWS * HFIELD_COLS
GOAL_DIM = 3
OBJECT_DIM = 12
#: all-MiniLM-L6-v2 sentence embeddings are 384-d.
TASK_EMBEDDING_DIM = 384

#: Every task id, in the order used by ``task_index``. Training tasks first.
TRAIN_TASKS = ("FT", "VT", "Incline", "Obstacle", "Patrol")
NOVEL_TASKS = ("Exploration", "Escape", "PointNav", "PushBoxIncline", "ManipulateBox")
TASK_NAMES = TRAIN_TASKS + NOVEL_TASKS

# Column layout of one proprioceptive token (spec 3.1).
XPOS = slice(0, 3)
#: The height column (body z): world height by default, or height above the ground under the torso
#: with ``gym.make(..., height_reference="ground")`` (see :data:`HEIGHT_REFERENCES`).
Z_COLUMN = 2
#: What the height column is measured from: ``"world"`` (z = 0 plane, MetaMorph's convention, the
#: default) or ``"ground"`` (the terrain under the torso: the same quantity on every task's ground,
#: flat, sloped or rugged, so one set of normalisation statistics fits every task).
HEIGHT_REFERENCES = ("world", "ground")
#: Rows of the ``object`` observation (4 x 3) that are positions relative to the torso (the box and
#: the goal); ``goal_range`` bounds their length as it bounds ``goal``'s.
OBJECT_POSITION_ROWS = (0, 3)


def check_goal_range(goal_range: float | None) -> float | None:
    """``goal_range`` as a float, or ``None`` (raw metres, the reference's observation).

    :raises ValueError: not a positive finite distance.
    """
    if goal_range is None:
        return None
    value = float(goal_range)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(
            f"goal_range is the distance (m) beyond which goal and object positions are observed at that distance; it must be > 0, got {goal_range}"
        )
    return value


XVELP = slice(3, 6)
XVELR = slice(6, 9)
XQUAT = slice(9, 13)
STATIC_BODY = slice(13, 30)
HINGE_SLOT_COLUMNS = (slice(30, 41), slice(41, 52))
#: Offsets inside a hinge slot: normalised qpos, qvel, then 9 static features.
HINGE_QPOS, HINGE_QVEL, HINGE_STATIC = 0, 1, slice(2, 11)
#: Dynamic columns (what changes every step); all other columns are static per morphology.
DYNAMIC_COLUMNS = np.array([*range(0, 13), 30, 31, 41, 42])


def observation_space() -> spaces.Dict:
    """The single observation space of every UNIMAL env (a flat ``spaces.Dict``, float32)."""

    def box(shape, low=-np.inf, high=np.inf):
        return spaces.Box(low=low, high=high, shape=shape, dtype=np.float32)

    return spaces.Dict(
        {
            "proprioceptive": box((MAX_TOKENS, PROPRIO_DIM)),
            "context": box((MAX_TOKENS, CONTEXT_DIM), -1.0, 1.0),
            "obs_padding_mask": box((MAX_TOKENS,), 0.0, 1.0),
            "act_padding_mask": box((ACTION_DIM,), 0.0, 1.0),
            "hfield": box((HFIELD_DIM,)),
            "goal": box((GOAL_DIM,)),
            "object": box((OBJECT_DIM,)),
            "task_embedding": box((TASK_EMBEDDING_DIM,), -1.0, 1.0),
            "task_index": box((1,), 0.0, float(len(TASK_NAMES) - 1)),
        }
    )


def action_space() -> spaces.Box:
    """``Box(-1, 1, (24,))``: two hinge slots per token; padded slots are ignored by the env."""
    return spaces.Box(low=-1.0, high=1.0, shape=(ACTION_DIM,), dtype=np.float32)
