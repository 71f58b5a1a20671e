"""``geonav demo``: the built-in walk-through on synthetic scenes A and B.

Synthesises scene A (residential) and scene B (campus), ingests them as
scene packages, cuts meta-tasks (150 m regions at 300 m) on A and whole-scene
tasks (75/45/15 m) on both, and draws each scene with its tasks, the camera
footprints and two rollouts through :class:`geonav.env.GeoNavEnv` (the
shortest-path oracle and a random policy).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from geonav.cliutil import positive_float, positive_int, seed_int

log = logging.getLogger(__name__)

SCENES = (("A", "residential", 0), ("B", "campus", 1))


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="synthesise scenes A and B, make tasks, draw rollouts")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--size", type=positive_float, default=1200.0, help="scene side in metres")
    p.add_argument("--gsd", type=positive_float, default=0.25, help="scene GSD in m/px")
    p.add_argument("--meta-tasks", type=positive_int, default=15, help="meta-tasks on scene A")
    p.add_argument("--seed", type=seed_int, default=0)
    p.add_argument("--force", action="store_true", help="re-create existing scenes")
    p.set_defaults(handler=run)


def ensure_scene(out: Path, name: str, kind: str, seed: int, size_m: float, gsd_m: float,
                 force: bool = False, progress=None, needs=None):
    """Open the scene package at ``out`` if it was made with these parameters, else make it
    (``needs``: a :class:`geonav.tiles.ingest.CoverageNeeds`, what it will be flown at)."""
    from geonav.errors import SceneError
    from geonav.scene import Scene
    from geonav.tiles.ingest import ingest_synthetic

    want = dict(kind=kind, seed=seed, size_m=size_m, gsd_m=gsd_m)
    if out.exists() and not force:
        try:
            scene = Scene.open(out)
            if scene.manifest.get("synthetic") == want and scene.name == name:
                return scene
        except SceneError as err:
            log.warning("re-creating %s: %s", out, err)
    return ingest_synthetic(kind, out=out, name=name, size_m=size_m, gsd_m=gsd_m, seed=seed,
                            overwrite=True, progress=progress, needs=needs)


def rollout(env, task_index: int, policy: str, seed: int) -> tuple[list, dict]:
    """Run one episode with the 'oracle' (shortest path) or 'random' policy."""
    obs, info = env.reset(seed=seed, options={"task": task_index})
    rng = np.random.default_rng(seed)
    cells = [info["cell"]]
    done = False
    while not done:
        if policy == "oracle":
            action = env.task_maps[task_index].shortest_path_action(info["cell"])
        else:
            action = int(rng.integers(4))
        obs, reward, terminated, truncated, info = env.step(action)
        cells.append(info["cell"])
        done = terminated or truncated
    return cells, info


def _not_a_demo_summary(path: Path) -> str | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        data = None
    ok = isinstance(data, dict) and data and all(
        isinstance(v, dict) and "kind" in v and "lattice" in v for v in data.values())
    return None if ok else "it is not a summary geonav demo wrote"


def check_demo_outputs(out: Path) -> None:
    """Refuse, before any work, a folder where the demo would replace files it did not write
    (a re-run replaces its own: the demo refreshes its outputs)."""
    from geonav.outputs import check_replaceable, not_a_geonav_picture, not_a_task_file

    names = [name for name, _, _ in SCENES]
    for path, kind, why_not in (
            [(out / "tasks" / f"{n}-{k}.json", "task file", not_a_task_file)
             for n in names for k in ("scene", "meta")]
            + [(out / f"scene-{n}.png", "picture", not_a_geonav_picture) for n in names]
            + [(out / "summary.json", "demo summary", _not_a_demo_summary)]):
        check_replaceable(path, kind, force=True, why_not=why_not)


def run(args: argparse.Namespace) -> int:
    from geonav.cliutil import progress_bar
    from geonav.env import GeoNavEnv
    from geonav.tasks import sample_meta_tasks, whole_scene_tasks
    from geonav.viz import draw_scene

    out = Path(args.out)
    check_demo_outputs(out)
    summary = {}
    from geonav.tiles.ingest import CoverageNeeds

    for name, kind, seed in SCENES:
        # whole-scene tasks at 75/45/15 m on both; 150 m meta-tasks at 300 m on A only
        needs = CoverageNeeds.paper() if name == "A" else CoverageNeeds(tasks=())
        scene = ensure_scene(out / "scenes" / name, name, kind, args.seed + seed, args.size,
                             args.gsd, args.force, progress_bar(f"scene {name}"), needs)
        scene_tasks = whole_scene_tasks(scene, (75.0, 45.0, 15.0), seed=args.seed + seed)
        scene_tasks.save(out / "tasks" / f"{name}-scene.json")
        sets = {"scene": scene_tasks}
        if name == "A":
            meta = sample_meta_tasks(scene, args.meta_tasks, seed=args.seed)
            meta.save(out / "tasks" / f"{name}-meta.json")
            sets["meta"] = meta
        env = GeoNavEnv(scene, scene_tasks)
        tracks = []
        for policy in ("oracle", "random"):
            cells, info = rollout(env, 0, policy, args.seed)
            tracks.append((env.tasks[0], cells, f"{policy} at {env.tasks[0].alt_m:g} m: "
                           f"{'reached' if info['success'] else 'missed'} in "
                           f"{info['steps']} steps"))
        picture = draw_scene(scene, out / f"scene-{name}.png", tasks=sets.get("meta", scene_tasks),
                             tracks=tracks)
        blocked = {f"{tm.task.alt_m:g}": int(tm.blocked.sum()) for tm in env.task_maps}
        summary[name] = dict(kind=kind, size_px=[scene.width, scene.height], gsd_m=scene.gsd_m,
                             tasks={k: len(v) for k, v in sets.items()},
                             lattice=list(env.tasks[0].lattice.shape),
                             blocked_cells_by_alt=blocked, picture=str(picture))
        print(f"scene {name} ({kind}): {scene.width}x{scene.height} px, "
              f"{len(scene_tasks)} whole-scene tasks on a {env.tasks[0].lattice.shape} lattice "
              f"(blocked cells by altitude {blocked})"
              + (f", {len(sets['meta'])} meta-tasks" if "meta" in sets else "")
              + f" -> {picture}")
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return 0
