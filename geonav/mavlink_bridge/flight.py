"""The flight loop: frame -> policy -> next lattice target -> arrival, on any vehicle.

This module is the driver and the only module of the bridge that touches
``geonav.policy`` (lazily, to load a checkpoint), so the backends never import torch.
The loop talks to a policy through :class:`Policy`: ``reset()``,
``act(image, target) -> int`` and a ``meta`` dict with ``obs_size_px``, ``alt_m``,
``step_m`` and ``fov_deg``.

Sequence (DESIGN.md "Deployment"): the plan (altitude, lattice, obstacles, target) is
checked before connecting (:mod:`~geonav.mavlink_bridge.plan`); then the phases, each
with one job: connect and preflight checks (:mod:`~geonav.mavlink_bridge.preflight`),
take-off and positioning, the step loop (:mod:`~geonav.mavlink_bridge.autonomy`), the
end action and the record (:mod:`~geonav.mavlink_bridge.ending`), sharing a
:class:`~geonav.mavlink_bridge.context.FlightContext`. The end action runs in a
``finally`` (Ctrl-C, SIGTERM, SIGHUP and any exception included). An operator takeover
ends autonomy without any further command. Every flight ends with an :data:`OUTCOMES`
word and its exit code (:mod:`~geonav.mavlink_bridge.outcome`).
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from geonav.errors import CheckpointError, ConfigError, FlightError
from geonav.geo import ScenePoint
from geonav.mavlink_bridge.autonomy import Verdict, step_loop, take_off_and_position
from geonav.mavlink_bridge.backends import open_vehicle
from geonav.mavlink_bridge.camera_source import FrameSource
from geonav.mavlink_bridge.context import FlightContext, Progress
from geonav.mavlink_bridge.ending import clear_autopilot_fence, end_action, record_result
from geonav.mavlink_bridge.outcome import OUTCOME_WORDS, OUTCOMES, FlightResult, classify
from geonav.mavlink_bridge.plan import (
    Cell,
    FlightConfig,
    FlightPlan,
    load_task,
    plan_flight,
    resolve_alt,
    validate_meta,
)
from geonav.mavlink_bridge.preflight import preflight
from geonav.mavlink_bridge.safety import OperatorTakeover, attribute_mode_change
from geonav.mavlink_bridge.signals import FlightInterrupted, StopSignals, stop_signals
from geonav.mavlink_bridge.vehicle import Vehicle

log = logging.getLogger(__name__)


class Policy(Protocol):
    """What the flight loop needs from a policy."""

    meta: dict[str, Any]

    def reset(self) -> None:
        """Start of an episode (clears recurrent state)."""

    def act(self, image: np.ndarray, target: np.ndarray) -> int:
        """Action 0..3 for the current (N, N, 3) uint8 view and the target view."""


class ScriptedPolicy:
    """A policy that replays fixed actions (tests and dry runs of the flight machinery).

    Args:
        actions: the actions, in order; the last one repeats when they run out.
        meta: ``obs_size_px``, ``alt_m``, ``step_m``, ``fov_deg``.
        delay_s: sleep this long in every ``act`` (to emulate a slow or stalled policy).
    """

    def __init__(self, actions: Sequence[int], meta: dict[str, Any], delay_s: float = 0.0) -> None:
        self.actions = list(actions)
        self.meta = dict(meta)
        self.delay_s = delay_s
        self.calls = 0

    def reset(self) -> None:
        self.calls = 0

    def act(self, image: np.ndarray, target: np.ndarray) -> int:
        if image.shape != target.shape or image.dtype != np.uint8:
            raise FlightError(f"policy input {image.shape} {image.dtype} vs target {target.shape}")
        if self.delay_s:
            time.sleep(self.delay_s)
        a = self.actions[min(self.calls, len(self.actions) - 1)]
        self.calls += 1
        return int(a)


def path_actions(start: Cell, target: Cell) -> list[int]:
    """Actions of a shortest obstacle-free path on the lattice (east first, then north)."""
    dx, dy = target[0] - start[0], target[1] - start[1]
    return [1 if dx > 0 else 2] * abs(dx) + [0 if dy > 0 else 3] * abs(dy)


def load_policy(checkpoint: str | Path) -> Policy:
    """``geonav.policy.inference.PolicyRunner.from_checkpoint`` (imported lazily), validated.

    Raises:
        CheckpointError: the policy package or the checkpoint is unusable.
    """
    try:
        from geonav.policy.inference import PolicyRunner  # type: ignore[import-not-found]
    except ImportError as err:
        raise CheckpointError(
            f"cannot load {checkpoint}: geonav.policy.inference.PolicyRunner is not available "
            f"({err}); install geonav with its policy package"
        ) from err
    runner = PolicyRunner.from_checkpoint(checkpoint)
    validate_meta(runner.meta, checkpoint)
    return runner  # type: ignore[no-any-return]


def run_flight(
    vehicle: Vehicle,
    scene: Any,
    policy: Policy,
    cfg: FlightConfig,
    out_dir: str | Path,
    progress: Progress | None = None,
    frames: FrameSource | None = None,
    *,
    plot: bool = True,
    warn: bool = True,
) -> FlightResult:
    """Fly ``policy`` on ``vehicle`` over ``scene`` (a :class:`geonav.scene.Scene`).

    Never raises for flight problems: they end the flight safely and are
    reported in the result (``outcome`` and ``exit_code``). SIGINT, SIGTERM and
    SIGHUP (when called from the main thread) end the flight like Ctrl-C.

    Args:
        plot: draw ``track.png`` before returning; False returns as soon as the flight
            has ended and its record is written (the result's :meth:`FlightResult.draw_track`
            draws it), so a command can say the outcome first.
        warn: log the plan's notes (an altitude clamp) as warnings (:func:`fly` has).

    Raises:
        ConfigError: the plan is invalid (checked before connecting).
    """
    with stop_signals() as sigs:
        ctx = FlightContext.begin(vehicle, scene, policy, cfg, out_dir, progress, frames, warn)
        result = _fly_phases(ctx, sigs)
    if plot:
        result.draw_track()
    return result


def _fly_phases(ctx: FlightContext, sigs: StopSignals) -> FlightResult:
    """The driver: preflight, take-off, steps; the end action always; then the record."""
    verdict = Verdict("missed", "")
    try:
        preflight(ctx)
        take_off_and_position(ctx)
        verdict = step_loop(ctx)
    except FlightInterrupted as err:
        verdict = Verdict("interrupted", f"interrupted by {err.args[0]}")
        ctx.rec.event(verdict.reason)
    except KeyboardInterrupt:
        verdict = Verdict("interrupted", "interrupted by the operator (Ctrl-C)")
        sigs.received = sigs.received or signal.SIGINT
        log.error("%s", verdict.reason)
        ctx.rec.event(verdict.reason)
    except FlightError as err:
        if isinstance(err, OperatorTakeover):
            err = attribute_mode_change(ctx.vehicle, err)
        verdict = Verdict(classify(err, ctx.phase), describe(err))
        # The result line says it; the log line is for -v.
        log.info("flight ended (%s): %s", verdict.outcome, verdict.reason)
        ctx.rec.event(f"{verdict.outcome}: {verdict.reason}")
    except Exception as err:  # any bug still ends in LAND/RTL below
        verdict = Verdict("safety_stop", f"unexpected error: {type(err).__name__}: {err}")
        log.exception("flight ended by an unexpected error")
        ctx.rec.event(verdict.reason)
    finally:
        sigs.may_raise = False  # the landing itself is never interrupted by a signal
        end = end_action(ctx, verdict)
        clear_autopilot_fence(ctx)
        if ctx.frames is not None:
            ctx.frames.close()
    return record_result(ctx, verdict, end, sigs)


def describe(err: FlightError) -> str:
    """The reason words of a flight error: its message (no class name; the messages of
    a refused command or a timeout say what was refused or awaited)."""
    return str(err)


def fly(
    policy: Policy | str | Path,
    scene: Any,
    *,
    target_cell: Cell | None = None,
    task: Any = None,
    connect: str | None = None,
    backend: str = "pymavlink",
    camera: str = "synthetic",
    start_cell: Cell | None = None,
    end: str = "land",
    dry_run: bool = False,
    autopilot: str = "px4",
    out_dir: str | Path = "flight",
    emulator_config: Any = None,
    progress: Progress | None = None,
    plot: bool = True,
    **config: Any,
) -> FlightResult:
    """Fly a checkpoint (or a Policy) on a scene; with ``dry_run`` against an in-process emulator.

    The plan (altitude, lattice, obstacles, start and target cells) is checked
    before any connection is opened.

    Args:
        policy: a checkpoint path or an object following :class:`Policy`.
        scene: a :class:`geonav.scene.Scene` or a scene package folder.
        target_cell: lattice cell to reach (in the task's lattice when ``task`` is given).
        task: a :class:`geonav.tasks.NavTask` (or ``FILE[:NAME]``): its region, step,
            altitude, target, step budget and obstacle model (``target_cell`` and
            ``config`` override them).
        connect: connection string (ignored with ``dry_run``).
        backend: ``pymavlink`` or ``mavsdk``.
        camera: ``synthetic``, ``opencv:N`` or rtsp URL.
        start_cell: start cell (None: under the take-off point).
        end: ``land`` or ``rtl``.
        dry_run: start a :class:`~geonav.mavlink_bridge.emulator.Emulator` with home at the
            start cell and fly against it.
        autopilot: emulator flavour for ``dry_run``.
        out_dir: folder for the flight record.
        emulator_config: an EmulatorConfig to use for ``dry_run`` (home is set from the scene).
        progress: callback (phase, fraction).
        plot: draw ``track.png`` before returning (False: the result's
            :meth:`FlightResult.draw_track` draws it, so the outcome can be said first).
        **config: further :class:`FlightConfig` fields.

    Raises:
        ConfigError: a bad plan or option (before connecting).
    """
    from geonav.scene import Scene

    if not isinstance(scene, Scene):
        scene = Scene.open(scene)
    if isinstance(task, (str, Path)):
        task = load_task(task)
    target_cell, config = _with_task(task, target_cell, config)
    cfg = FlightConfig(
        target_cell=(int(target_cell[0]), int(target_cell[1])),
        start_cell=None if start_cell is None else (int(start_cell[0]), int(start_cell[1])),
        end=end,
        camera=camera,
        **config,
    )
    pol: Policy = load_policy(policy) if isinstance(policy, (str, Path)) else policy
    plan = plan_flight(scene, pol.meta, cfg)  # before connecting: bad plans fail fast
    emu = None
    if dry_run:
        cfg, emu = _dry_run_emulator(scene, plan, cfg, autopilot, emulator_config)
        connect = emu.connect_url
    if connect is None:
        raise ConfigError("no connection: give --connect URL or --dry-run")
    try:
        vehicle = open_vehicle(connect, backend)
        return run_flight(vehicle, scene, pol, cfg, out_dir, progress, plot=plot, warn=False)
    finally:
        if emu is not None:
            emu.stop()


def _with_task(task: Any, target_cell: Cell | None,
               config: dict[str, Any]) -> tuple[Cell, dict[str, Any]]:
    """The target and the FlightConfig fields, the task's where the caller gave none."""
    config = dict(config)
    if task is not None:
        for key, value in (
            ("region_m", tuple(task.region_m)),
            ("step_m", task.step_m),
            ("alt_m", task.alt_m),
            ("max_steps", task.max_steps),
            ("obstacles", task.obstacles),
        ):
            if config.get(key) is None:
                config[key] = value
        if target_cell is None:
            target_cell = tuple(task.target_cell)
    if target_cell is None:
        raise ConfigError("no target: give --target IX,IY or --task FILE[:NAME]")
    return target_cell, {k: v for k, v in config.items() if v is not None}


def _dry_run_emulator(scene: Any, plan: FlightPlan, cfg: FlightConfig, autopilot: str,
                      emulator_config: Any) -> tuple[FlightConfig, Any]:
    """A started emulator with home at the start cell (the free cell nearest the
    lattice's centre when none was given), and the config with that start."""
    from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig

    if cfg.start_cell is None:
        nx, ny = plan.lattice.shape
        free = [(ix, iy) for ix in range(nx) for iy in range(ny) if not plan.blocked[ix, iy]]
        centre = (nx // 2, ny // 2)
        cfg = replace(
            cfg,
            start_cell=min(free, key=lambda c: abs(c[0] - centre[0]) + abs(c[1] - centre[1])),
        )
    assert cfg.start_cell is not None
    home = scene.frame.to_lonlat(plan.lattice.center(cfg.start_cell), 0.0)
    # A dry run is a rehearsal at 3x emulated speed; the emulator bounds its emulated
    # time per iteration, so a busy machine slows the vehicle instead of jumping it.
    ec = emulator_config or EmulatorConfig(
        autopilot=autopilot,
        time_scale=3.0,
        boot_s=1.0,
        prearm_s=2.0,
        origin_s=1.0,
        local_position_s=1.5,
    )
    ec.home = home
    ec.autopilot = autopilot if emulator_config is None else ec.autopilot
    return cfg, Emulator(ec).start()


__all__ = [
    "OUTCOMES",
    "OUTCOME_WORDS",
    "Cell",
    "FlightConfig",
    "FlightInterrupted",
    "FlightPlan",
    "FlightResult",
    "Policy",
    "ScenePoint",
    "ScriptedPolicy",
    "fly",
    "load_policy",
    "load_task",
    "path_actions",
    "plan_flight",
    "resolve_alt",
    "run_flight",
    "stop_signals",
    "validate_meta",
]
