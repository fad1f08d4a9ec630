"""Several robots per MuJoCo Warp world: graph nodes and physics time against one model per robot.

MuJoCo Warp batches *worlds* of one compiled model: per-world fields are parameters (masses, sizes,
``geom_dataid``, ...), never the kinematic tree, so robots of different shapes cannot share a model
across worlds. The batched backend therefore runs one model (one captured graph) per robot. The only
way to step several different robots in one model is to put them in the same world: one compiled
scene holding ``K`` robots side by side on one floor, kept from touching each other by collision
bits (robot geoms ``contype=2, conaffinity=1``, the arena's ``contype=1, conaffinity=2``: robots
collide with the arena, never with each other). This probe measures, for FT's flat floor and the
first ``K`` robots of a set:

* **graph nodes per substep** of ``mjw.step`` (kernels, memsets, copies, conditional nodes, counted
  as it is captured) for the merged scene and for each robot's own model;
* **physics time per substep** of ``W`` worlds: the merged scene's graph, against the ``K`` robots'
  graphs (on CUDA each on its own stream, as the backend runs them; on CPU one after the other);
* **first-step time** (kernel compilation for the model's sizes; cached in ``~/.cache/warp``).

It does not change the backend; it tells whether merging would pay (it costs a scene builder,
per-robot resets inside a world, all robots of a world on the same terrain variant, and a solve
whose iterations run to the slowest robot of the world).

Usage::

    python benchmarks/robots_per_world.py [--robots 1 4 8] [--worlds 8] [--device cpu|cuda]

Writes ``results/robots_per_world_<device>.md``.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from contextlib import nullcontext
from datetime import date
from pathlib import Path

import mujoco
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from batched_throughput import _version, _WarpCounter  # noqa: E402

RESULTS = Path(__file__).resolve().parent.parent / "results"
#: contacts and constraint rows per robot in a world (as unimal_envs.batched.worlds allocates per world)
CONTACTS, CONSTRAINTS = 96, 4 * 96 + 64


def merged_scene(env, robots: int, spacing: float) -> mujoco.MjModel:
    """The first robot's FT world with ``robots - 1`` more robots attached ``spacing`` m apart in y,
    robots colliding with the arena only."""
    from unimal_envs.robot import Robot

    spec, _ = env.world_spec(0)
    for i in range(1, robots):
        robot = Robot(env.morphologies[i])
        pos, quat = env.task.spawn_pose(robot)
        frame = spec.worldbody.add_frame(pos=[0, spacing * i, 0])
        frame.attach_body(robot.build_spec(pos, quat).worldbody.first_body(), f"r{i}/", "")
    model = spec.compile()
    arena = model.geom_bodyid == 0
    model.geom_contype[:] = np.where(arena, 1, 2)
    model.geom_conaffinity[:] = np.where(arena, 2, 1)
    return model


def measure(models: list[mujoco.MjModel], worlds: int, device: str, repeats: int, settle: int) -> dict:
    """Nodes per substep of each model's ``mjw.step``, first-step seconds, and seconds per substep of
    all models' graphs replayed together."""
    import mujoco_warp as mjw
    import warp as wp

    graphs, nodes, first = [], [], 0.0
    with wp.ScopedDevice(device):
        for model in models:
            per_world = max(1, round(model.nv / 18))  # robots in this model (about 18 dofs each)
            m = mjw.put_model(model)
            d = mjw.make_data(model, nworld=worlds, nconmax=CONTACTS * per_world, njmax=CONSTRAINTS * per_world)
            stream = wp.Stream(device) if device != "cpu" else None
            start = time.perf_counter()
            mjw.step(m, d)
            wp.synchronize()
            first += time.perf_counter() - start
            for _ in range(settle):  # the robots land: contacts, as in training
                mjw.step(m, d)
            with wp.ScopedStream(stream) if stream is not None else nullcontext():  # launches go to the current stream
                with _WarpCounter() as counter, wp.ScopedCapture(device=device, stream=stream) as capture:
                    mjw.step(m, d)
            graphs.append((capture.graph, stream, m, d))
            nodes.append(counter.counts)
        wp.synchronize()
        start = time.perf_counter()
        for _ in range(repeats):
            for graph, stream, _, _ in graphs:
                wp.capture_launch(graph, stream=stream)
        wp.synchronize()
        seconds = (time.perf_counter() - start) / repeats
    total = {k: sum(n[k] for n in nodes) for k in nodes[0]}
    return {"nodes": total, "first": first, "substep": seconds}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", nargs="*", type=int, default=[1, 4, 8], help="robots per world (K)")
    parser.add_argument("--worlds", type=int, default=8, help="worlds (W) of each model")
    parser.add_argument("--device", default="cpu", help="Warp device (cpu, cuda)")
    parser.add_argument("--repeats", type=int, default=50, help="timed substeps")
    parser.add_argument("--spacing", type=float, default=3.0, help="metres between the robots of a world")
    parser.add_argument("--settle", type=int, default=200, help="substeps before timing (the robots land)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    import warp as wp

    import unimal_envs  # noqa: F401
    from unimal_envs.env import UnimalEnv
    from unimal_envs.morphology.loader import morphology_files

    wp.config.quiet = True
    torch.set_num_threads(1)
    device = "cuda:0" if args.device == "cuda" else args.device
    env = UnimalEnv("FT", morphology_files("train")[: max(args.robots)])
    rows = []
    for k in args.robots:
        merged = measure([merged_scene(env, k, args.spacing)], args.worlds, device, args.repeats, args.settle)
        separate = measure([env.world_spec(i)[0].compile() for i in range(k)], args.worlds, device, args.repeats, args.settle)
        rows.append((k, merged, separate))
        print(
            f"K={k}: merged {merged['substep'] * 1e3:.2f} ms, {merged['nodes']['kernels']} kernels; "
            f"separate {separate['substep'] * 1e3:.2f} ms, {separate['nodes']['kernels']} kernels",
            flush=True,
        )

    nodes = lambda n: n["kernels"] + n["memsets"] + n["copies"] + n["conditionals"]  # noqa: E731
    command = "python benchmarks/robots_per_world.py " + " ".join(argv if argv is not None else sys.argv[1:])
    name = torch.cuda.get_device_name(0) if device.startswith("cuda") else "CPU Warp (one core)"
    lines = [
        "# Several robots per MuJoCo Warp world vs one model per robot (physics only)",
        "",
        f"Command: `{command.strip()}`  ",
        f"Device: {name}; {platform.machine()}, Python {platform.python_version()}, mujoco-warp {_version('mujoco-warp')}, "
        f"warp-lang {_version('warp-lang')}; date {date.today()}  ",
        f"FT's flat floor, the first K robots of `train`, {args.worlds} worlds per model, zero controls, timed after "
        f"{args.settle} substeps (the robots stand on the floor); one `mjw.step` (one substep; a control step is 4) "
        f"captured as a graph and replayed {args.repeats} times (the state moves on). "
        "*Merged*: one model whose world holds the K robots side by side (colliding with the floor, not with each "
        "other). *Separate*: K models, one per robot (the batched backend today)"
        + (", their graphs each on its own stream." if device != "cpu" else ", their graphs one after the other."),
        "",
        "| robots per world (K) | merged: nv | merged: graph nodes | merged: ms per substep | separate: graph nodes "
        "| separate: ms per substep | merged / separate time | first step (s): merged, separate |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k, merged, separate in rows:
        nv = merged_scene(env, k, args.spacing).nv
        lines.append(
            f"| {k} | {nv} | {nodes(merged['nodes'])} | {merged['substep'] * 1e3:.2f} | {nodes(separate['nodes'])} "
            f"| {separate['substep'] * 1e3:.2f} | {merged['substep'] / separate['substep']:.2f} "
            f"| {merged['first']:.1f}, {separate['first']:.1f} |"
        )
    out = args.out or RESULTS / f"robots_per_world_{'cpu' if device == 'cpu' else 'cuda'}.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
