"""The emulated vehicle's motion and autopilot state machine.

:class:`PhysicsMixin` is a kinematic multicopter: a point mass under a second-order
position loop with speed and acceleration limits (it overshoots and settles like a
real copter), the mode logic that decides where it steers (hold, land, RTL with its
return and descent), boot, EKF origin, offboard loss and the auto-disarms, and the
autopilot's own lon/lat <-> NED formula (:mod:`geonav.mavlink_bridge.frames`).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from geonav.errors import FlightError
from geonav.geo import LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.emulator_config import EmulatorFields
from geonav.mavlink_bridge.frames import local_frame

log = logging.getLogger("geonav.mavlink_bridge.emulator")


class PhysicsMixin(EmulatorFields):
    """Motion, modes, origin and disarm logic (mixed into :class:`Emulator`)."""

    def _event(self, text: str) -> None:
        self.events.append((self.t_s, text))
        log.debug("emulator t=%.2f: %s", self.t_s, text)

    def _position_valid(self) -> bool:
        return (
            self.origin is not None and not self._gps_lost and self.t_s >= self.cfg.local_position_s
        )

    def _set_mode(self, name: str, why: str = "") -> None:
        if name != self.mode:
            self.mode = name
            self._event(f"mode {name}" + (f" ({why})" if why else ""))
        if name in ("land", "rtl", "hold", "loiter", "posctl", "stabilize", "brake", "althold"):
            # Leaving autonomy: hold (or land) where the vehicle is now.
            self.target = self.pos.copy() if not self.landed else None
            self._rtl_phase = "return" if name == "rtl" else ""

    def _disarm(self, why: str) -> None:
        if self.armed:
            self.armed = False
            self._armed_at = None
            self._took_off = False
            self._touchdown_at = None
            self.target = None
            self.failsafe = ""
            self._event(f"disarmed ({why})")

    def _step(self, dt: float) -> None:
        cfg = self.cfg
        # Boot end: a mode set during boot is undone.
        if self.booted and self._boot_mode is not None:
            if self.mode != self._boot_mode:
                self._event(f"mode {self._boot_mode} (boot finished, mode reset)")
                self.mode = self._boot_mode
            self._boot_mode = None
        if self.origin is None and cfg.gps and self.t_s >= cfg.origin_s and not self._gps_lost:
            self._set_origin(self.home, source="GPS")
        # PX4 offboard loss.
        if self.flavour == M.PX4 and self.mode == "offboard":
            if self.t_s - self._last_sp_t > cfg.offboard_loss_s:
                self._statustext(4, "Failsafe: offboard control lost")
                self._set_mode(cfg.offboard_loss_action, why="offboard loss")
        # Auto-disarm before take-off.
        if self.armed and not self._took_off and self._armed_at is not None:
            if self.t_s - self._armed_at > cfg.disarm_delay_s:
                self._statustext(4, "Disarmed: no takeoff")
                self._disarm("auto-disarm, no take-off")
        self._safety_step(dt)
        self._control(dt)
        self.track.append((self.t_s, float(self.pos[0]), float(self.pos[1]), float(self.pos[2])))
        if len(self.track) > 200_000:
            del self.track[:100_000]

    def _goal(self) -> np.ndarray | None:
        """Position the controller steers to now, by mode."""
        if not self.armed:
            return None
        if self.mode == "land":
            goal = self.target.copy() if self.target is not None else self.pos.copy()
            goal[2] = self.pos[2] + 5.0  # descend at the land speed limit
            return goal
        if self.mode == "rtl":
            return None  # handled in _control
        return self.target

    def _control(self, dt: float) -> None:
        cfg = self.cfg
        if not self.armed:
            self.vel[:] = 0.0
            return
        vz_limit = cfg.max_climb_mps
        goal = self._goal()
        if self.mode == "rtl":
            home = np.array([0.0, 0.0, 0.0]) if self.origin is None else self._home_ned()
            if self._rtl_phase == "return":
                goal = np.array([home[0], home[1], min(self.pos[2], -cfg.rtl_alt_m)])
                if np.hypot(*(self.pos[:2] - home[:2])) < 0.5 and np.linalg.norm(self.vel) < 0.5:
                    self._rtl_phase = "land"
            if self._rtl_phase == "land":
                goal = np.array([home[0], home[1], self.pos[2] + 5.0])
        if self.mode in ("land", "rtl") and goal is not None and goal[2] > self.pos[2]:
            vz_limit = cfg.land_speed_mps
            if self.target is None:
                self.target = self.pos.copy()
        if goal is None:
            goal = self.pos.copy() if not self.landed else None
        if goal is None:
            self.vel[:] = 0.0
            return
        if self.landed and goal[2] >= self.pos[2] - 0.05:
            # On the ground and not asked to climb.
            self.vel[:] = 0.0
            self._maybe_auto_disarm_landed()
            return
        wn = 2 * math.pi * cfg.natural_freq_hz
        acc = wn * wn * (goal - self.pos) - 2 * cfg.damping * wn * self.vel
        # Limits: horizontal acceleration norm, vertical acceleration, speeds.
        ah = np.hypot(acc[0], acc[1])
        if ah > cfg.max_accel_mps2:
            acc[:2] *= cfg.max_accel_mps2 / ah
        acc[2] = float(np.clip(acc[2], -cfg.max_accel_mps2, cfg.max_accel_mps2))
        self.vel += acc * dt
        vh = np.hypot(self.vel[0], self.vel[1])
        if vh > cfg.max_speed_mps:
            self.vel[:2] *= cfg.max_speed_mps / vh
        self.vel[2] = float(np.clip(self.vel[2], -cfg.max_climb_mps, vz_limit))
        self.pos += self.vel * dt
        if self.pos[2] < -0.3 and self.landed:
            self.landed = False
            self._took_off = True
            self._touchdown_at = None
            self._event("airborne")
        if self.pos[2] >= 0.0:
            self.pos[2] = 0.0
            self.vel[2] = min(self.vel[2], 0.0)
            if not self.landed and self.vel[2] >= -0.01 and goal[2] >= 0.0:
                self.landed = True
                self.vel[:] = 0.0
                self._touchdown_at = self.t_s
                self._event("landed")
        if self.landed:
            self._maybe_auto_disarm_landed()

    def _maybe_auto_disarm_landed(self) -> None:
        if (
            self._touchdown_at is not None
            and self.t_s - self._touchdown_at > self.cfg.land_disarm_s
        ):
            self._disarm("landed")

    def _home_ned(self) -> np.ndarray:
        if self.origin is None:
            return np.zeros(3)
        n, e = self._to_ned(self.home)
        return np.array([n, e, 0.0])

    def _set_origin(self, origin: LonLat, source: str) -> None:
        self.origin = origin
        # The autopilot's own lon/lat <-> NED formula (ArduPilot flat earth, PX4 aeqd).
        self._frame = local_frame(self.flavour, origin)
        self._event(f"EKF origin set from {source}: {origin}")
        self._send_origin()
        self._send_home()

    def _to_ned(self, q: LonLat) -> tuple[float, float]:
        assert self._frame is not None
        return self._frame.to_ne(q)

    def lonlat_of(self, north_m: float, east_m: float, down_m: float = 0.0) -> LonLat:
        """WGS 84 position of a point of the local NED frame (the autopilot's formula)."""
        if self.origin is None or self._frame is None:
            raise FlightError("emulator EKF origin not set yet")
        lon, lat = self._frame.to_lonlat(float(north_m), float(east_m))
        return LonLat(lon, lat, self.origin.alt_m - float(down_m))
