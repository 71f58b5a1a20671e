"""What the phases of one flight share: :class:`FlightContext`.

The flight is a short driver (:func:`geonav.mavlink_bridge.flight.run_flight`) over
phases that each do one job (:mod:`~geonav.mavlink_bridge.preflight`,
:mod:`~geonav.mavlink_bridge.autonomy`, :mod:`~geonav.mavlink_bridge.ending`); they
hand each other this record: the vehicle, the plan, the record being written, what
preflight placed (frame conversion, fence, start and target), the safety machinery
(watchdog, setpoint pump), and the progress so far (phase, cell, steps). Its small
methods are the checks every phase runs while the vehicle moves: the track and
battery samples, the measured-position fence and the battery floor.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geonav.errors import SafetyViolation
from geonav.geo import LocalNED, ScenePoint
from geonav.mavlink_bridge.camera_source import FrameSource
from geonav.mavlink_bridge.conversion import TargetPlanner
from geonav.mavlink_bridge.plan import Cell, FlightConfig, FlightPlan, plan_flight
from geonav.mavlink_bridge.pump import SetpointPump
from geonav.mavlink_bridge.record import FlightRecorder
from geonav.mavlink_bridge.safety import BatteryLow, Geofence, Watchdog
from geonav.mavlink_bridge.sequence import Timeouts
from geonav.mavlink_bridge.vehicle import Vehicle, VehicleState

Progress = Callable[[str, float], None]


@dataclass
class FlightContext:
    """One flight's shared state, filled in phase by phase.

    Attributes:
        vehicle, scene, policy, cfg: what :func:`run_flight` was given.
        plan: the checked plan (re-made at the vehicle's altitude on a takeover).
        rec: the flight record being written.
        report: progress callback (phase, fraction).
        frames: the camera (None until preflight chose one, unless given).
        phase: ``preflight``, ``arming``, ``takeoff``, ``takeover``, ``autonomy``.
        we_fly: geonav armed the vehicle (or took an airborne one over): only then
            does it command LAND/RTL at the end.
        airborne: the vehicle was already flying when geonav connected.
        planner, fence, watchdog, pump: set by preflight.
        here_scene: where the vehicle was at preflight (scene metres).
        start_cell, start_pt, target_pt, target_img: the start, the target and its view.
        cell: the cell the vehicle is over (None before the start cell is reached).
        steps: policy steps done (see :func:`~geonav.mavlink_bridge.autonomy.step_loop`).
        flown_steps: steps that moved the vehicle to a new cell.
        fence_uploaded: the autopilot holds geonav's fence (to be cleared at the end).
        latencies_ms: frame -> setpoint latency per step.
        notes: warnings the operator must see (altitude clamp, obstacle refusals).
    """

    vehicle: Vehicle
    scene: Any
    policy: Any
    cfg: FlightConfig
    plan: FlightPlan
    rec: FlightRecorder
    report: Progress
    frames: FrameSource | None = None
    phase: str = "preflight"
    we_fly: bool = False
    airborne: bool = False
    planner: TargetPlanner | None = None
    fence: Geofence | None = None
    watchdog: Watchdog | None = None
    pump: SetpointPump | None = None
    here_scene: ScenePoint | None = None
    start_cell: Cell | None = None
    start_pt: ScenePoint | None = None
    target_pt: ScenePoint | None = None
    target_img: np.ndarray | None = None
    cell: Cell | None = None
    steps: int = 0
    flown_steps: int = 0
    fence_uploaded: bool = False
    latencies_ms: list[float] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    _last_sample_t: float = 0.0

    @classmethod
    def begin(
        cls,
        vehicle: Vehicle,
        scene: Any,
        policy: Any,
        cfg: FlightConfig,
        out_dir: str | Path,
        progress: Progress | None = None,
        frames: FrameSource | None = None,
        warn: bool = True,
    ) -> FlightContext:
        """Plan the flight (ConfigError before connecting) and open its record with a header."""
        plan = plan_flight(scene, policy.meta, cfg, warn=warn)
        rec = FlightRecorder(out_dir)
        ctx = cls(vehicle, scene, policy, cfg, plan, rec, progress or (lambda phase, f: None),
                  frames, notes=list(plan.notes))
        rec.write(
            "header",
            scene=scene.name,
            bounds_m=scene.bounds_m,
            scene_origin=scene.origin,
            config=asdict(cfg),
            policy_meta=policy.meta,
            alt_m=plan.alt_m,
            step_m=plan.step_m,
            fence_margin_m=plan.margin_m,
            lattice_region_m=plan.lattice.region_m,
            blocked_cells=[list(map(int, c)) for c in np.argwhere(plan.blocked)],
        )
        for note in ctx.notes:
            rec.event(note)
        # The autopilot's own messages go into the record as they come (folded).
        vehicle.on_statustext = lambda severity, text: rec.write(
            "statustext", severity=severity, text=text)
        return ctx

    # ------------------------------------------------------------------ views
    @property
    def t(self) -> Timeouts:
        """The per-phase timeouts."""
        return self.cfg.timeouts

    @property
    def alt_m(self) -> float:
        """Flight altitude above the take-off point."""
        return self.plan.alt_m

    @property
    def start_xy(self) -> tuple[float, float] | None:
        """The start cell's centre (scene metres), once known."""
        return None if self.start_pt is None else (self.start_pt.x_m, self.start_pt.y_m)

    @property
    def target_xy(self) -> tuple[float, float] | None:
        """The target cell's centre (scene metres), once known."""
        return None if self.target_pt is None else (self.target_pt.x_m, self.target_pt.y_m)

    # ----------------------------------------------------- checks while moving
    def sample(self, s: VehicleState, phase_name: str | None = None) -> None:
        """Record the measured track and the battery (every phase: climb, steps, return,
        landing)."""
        now = time.monotonic()
        if now - self._last_sample_t < 0.1:
            return
        self._last_sample_t = now
        self.rec.battery(s.battery_pct, s.battery_v)
        if self.planner is None or s.position is None:
            return
        p, alt = self.planner.to_scene(s.position)
        self.rec.sample(p.x_m, p.y_m, phase_name or self.phase, alt)

    def check_battery(self, s: VehicleState) -> None:
        """The battery against ``--min-battery``.

        Raises:
            BatteryLow: below it: the flight ends with the end action.
        """
        floor = self.cfg.min_battery_pct
        if floor > 0 and s.battery_pct is not None and s.battery_pct < floor:
            raise BatteryLow(
                f"battery at {s.battery_pct:.0f}% is below --min-battery {floor:g}%"
                + (f" ({s.battery_v:.2f} V)" if s.battery_v is not None else "")
            )

    def check_position(self, s: VehicleState) -> None:
        """The measured position against the fence (widened by the overshoot allowance).

        Raises:
            SafetyViolation: the vehicle breached the fence.
        """
        if self.fence is None or self.planner is None or s.position is None:
            return
        p, _ = self.planner.to_scene(s.position)
        why = self.fence.position_violation(p)
        if why is not None:
            raise SafetyViolation(f"position fence: {why}")

    def check_setpoint(self, ned: LocalNED) -> None:
        """A setpoint against the fence and its altitude band (the pump's fence check).

        Raises:
            SafetyViolation: the setpoint would leave the fence; it is never sent.
        """
        assert self.planner is not None and self.fence is not None
        p, alt = self.planner.to_scene(ned)
        self.fence.check(p)
        if not (self.fence.min_alt_m - 0.5 <= alt <= self.fence.max_alt_m + 0.5):
            raise SafetyViolation(f"setpoint altitude {alt:.1f} m outside the altitude band")

    def in_flight_check(self) -> None:
        """What runs in every wait while the vehicle moves: track and battery samples,
        position fence, battery floor."""
        st = self.vehicle.state()
        self.sample(st)
        self.check_position(st)
        self.check_battery(st)
