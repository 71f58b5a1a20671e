"""``geonav tasks make``: cut a scene into navigation tasks (JSON)."""

from __future__ import annotations

import argparse

from geonav.cliutil import (
    add_command_group,
    positive_float,
    positive_floats,
    positive_int,
    seed_int,
)


def _fraction(text: str) -> float:
    value = positive_float(text)
    if value > 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be within 0..1 (e.g. 0.99)")
    return value


def _limit(text: str) -> float | None:
    """A chance limit in (0, 1], or 'none' for no limit."""
    if text.strip().lower() == "none":
        return None
    value = positive_float(text)
    if value > 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be within (0, 1] or 'none'")
    return value


def add_parser(sub: argparse._SubParsersAction) -> None:
    tsub = add_command_group(sub, "tasks", help="make navigation task sets",
                             metavar="TASKS_COMMAND")
    p = tsub.add_parser("make", help="meta-tasks (regions at 300 m) or whole-scene tasks")
    p.add_argument("scene", help="scene package folder")
    p.add_argument("--kind", choices=["meta", "scene"], default="meta",
                   help="meta: COUNT regions of SIZE m at ALT; scene: one task per altitude")
    p.add_argument("--count", type=positive_int, default=15,
                   help="meta-tasks to sample (default 15)")
    p.add_argument("--size", type=positive_float, help="region side in metres (meta default 150; "
                   "scene default: the whole scene less the view margin)")
    p.add_argument("--alt", type=positive_float, default=300.0,
                   help="meta-task altitude (default 300)")
    p.add_argument("--alts", type=positive_floats, default=(75.0, 45.0, 15.0),
                   help="whole-scene altitudes (default 75,45,15)")
    p.add_argument("--step", type=positive_float, default=15.0,
                   help="lattice step in metres (default 15)")
    p.add_argument("--max-steps", type=positive_int,
                   help="episode cap (default: meta 70, scene 120)")
    p.add_argument("--obs-size", type=positive_int, default=84, help="camera image side in px")
    p.add_argument("--fov", type=positive_float, default=90.0,
                   help="camera field of view in degrees")
    p.add_argument("--min-coverage", type=_fraction, default=0.99, metavar="FRACTION",
                   help="least fraction of valid imagery in the view of a target or start "
                   "(default 0.99)")
    p.add_argument("--max-blind", type=_limit, default=0.3, metavar="SR",
                   help="keep only targets whose best view-blind policy (knows the target, "
                   "ignores the view: a fixed action bias) succeeds at most SR of the time, "
                   "with starts on every side of the target, so the tasks need the view "
                   "(default 0.3; 'none' keeps any target, e.g. corner targets)")
    p.add_argument("--max-random-walk", type=_limit, default=None, metavar="SR",
                   help="keep only targets a uniform random walk reaches at most SR of the "
                   "time (default none)")
    p.add_argument("--seed", type=seed_int, default=0)
    p.add_argument("-o", "--out", required=True, help="task set JSON to write")
    p.add_argument("--force", action="store_true",
                   help="replace an existing task file (only one geonav wrote)")
    p.set_defaults(handler=run_make)


def run_make(args: argparse.Namespace) -> int:
    from geonav.outputs import check_replaceable, not_a_task_file, output_lock

    with output_lock(args.out, "-o"):
        check_replaceable(args.out, "task file", force=getattr(args, "force", False),
                          why_not=not_a_task_file)
        return _make(args)


def _make(args: argparse.Namespace) -> int:
    from geonav.camera import Camera
    from geonav.cliutil import progress_bar
    from geonav.scene import Scene
    from geonav.tasks import sample_meta_tasks, whole_scene_tasks

    # Long on a large scene (the default one took 14.6 min, silent): the bar on a
    # terminal, a line every ~30 s in a log, through the chance figures' one long call.
    progress = progress_bar("tasks")
    scene = Scene.open(args.scene)
    camera = Camera(args.obs_size, args.fov)
    if args.kind == "meta":
        ts = sample_meta_tasks(scene, args.count, size_m=args.size or 150.0, alt_m=args.alt,
                               step_m=args.step, max_steps=args.max_steps or 70, seed=args.seed,
                               camera=camera, min_coverage=args.min_coverage,
                               max_random_walk=args.max_random_walk, max_blind=args.max_blind,
                               progress=progress)
    else:
        alts = list(args.alts)
        ts = whole_scene_tasks(scene, alts, step_m=args.step, max_steps=args.max_steps or 120,
                               seed=args.seed, size_m=args.size, camera=camera,
                               min_coverage=args.min_coverage,
                               max_random_walk=args.max_random_walk, max_blind=args.max_blind,
                               progress=progress)
    from geonav.difficulty import describe, taskset_difficulty

    progress("chance figures", 0.0)
    ts.meta["difficulty"] = diff = taskset_difficulty(ts, scene)
    progress("chance figures", 1.0)
    ts.save(args.out)
    t = ts.tasks[0]
    nx, ny = t.lattice.shape
    print(f"{len(ts)} {args.kind} task(s) on scene {scene.name}: {nx}x{ny} cells of "
          f"{t.step_m:g} m at {', '.join(f'{x.alt_m:g}' for x in ts.tasks[:4])} m -> {args.out}")
    print(f"chance: {describe(diff)} (exact, DP over the lattice; "
          f"per task in the JSON's meta.difficulty)")
    return 0
