"""Copy a single env's episode into one world of a batched env (for the agreement tests)."""

from __future__ import annotations

import torch
import warp as wp

from unimal_envs.env import UnimalEnv


def mirror_world(benv, world: int, env: UnimalEnv) -> dict[str, torch.Tensor]:
    """Put world ``world`` of ``benv`` in the state of ``env``'s current episode (same task, and
    the world's robot must be the env's): robot and prop state, terrain, the task's goal and
    progress. Returns the batched observations afterwards."""
    block, rows = next((b, r) for b, r in benv._rows() if r.start <= world < r.stop)
    local = world - rows.start
    group = block.groups[local // block.worlds]
    w = local % block.worlds
    assert group.morphology.name == env.morphology.name, "the world simulates another robot"
    model, data = env.model, env.data
    group.qpos[w] = torch.as_tensor(data.qpos, dtype=torch.float32)
    group.qvel[w] = torch.as_tensor(data.qvel, dtype=torch.float32)
    group.qacc_warmstart[w] = 0.0
    group.time[w] = 0.0
    mask = torch.zeros(block.n, dtype=torch.bool)
    mask[local] = True
    if block.pool is not None:
        # The single env's terrain becomes variant 0 of the pool, and this world uses it.
        grid = env.arena.grid
        block.heightmaps.padded[0] = torch.as_tensor(grid.padded.reshape(-1))
        if group.variant_dataid is not None:  # the single world's one height field -> variant 0's asset
            size, source = grid.heights.size, int(model.hfield_adr[0])
            target = int(group.mj_model.hfield_adr[group.variant_dataid[0]])
            wp.to_torch(group.model.hfield_data)[target : target + size] = torch.as_tensor(model.hfield_data[source : source + size])
        if group.obstacle_ids.size:
            block.layout[0] = torch.as_tensor(env.arena.layout, dtype=torch.float32)
        block.variant[local] = 0
        group_mask = torch.zeros(group.worlds, dtype=torch.bool)
        group_mask[w] = True
        group.select_terrain(group_mask, block.variant[local - w : local - w + group.worlds], block.layout)
    group.launch("sync")
    task, single = block.task, env.task
    readings = block.read()
    state = {}
    for name in ("goals_reached", "steps_at_goal"):
        if hasattr(single, name):
            state[name] = float(getattr(single, name))
    if hasattr(task, "visited"):
        task.visited[local] = torch.as_tensor(single.visited)
    if hasattr(task, "goal"):
        task.goal[local] = torch.as_tensor(single.goal, dtype=torch.float32)
        if hasattr(task, "observed_goal"):
            task.observed_goal[local] = task.goal[local]
    if hasattr(task, "distance"):
        task.distance[local] = task.goal_distance(readings)[local]
    if hasattr(task, "reach_distance"):
        task.reached[local] = bool(single.reached)
        task.reach_distance[local] = readings.reach[local]
        task.goal_distance[local] = task._box_goal_distance(readings)[local]
        task.box_start[local] = readings.box[local]
    for name, value in state.items():
        getattr(task, name)[local] = value
    benv.steps[world] = 0
    return benv._observe()
