"""The flight's phases one at a time against the MAVLink emulator (issue 35): preflight,
take-off and positioning, the step loop, the end action, the record; and the failsafe
attribution they rely on."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from flight_helpers import FAST, META, START, TARGET, fast_emulator

from geonav.errors import FlightError
from geonav.geo import LocalNED
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.autonomy import Verdict, step_loop, take_off_and_position
from geonav.mavlink_bridge.backends import open_vehicle
from geonav.mavlink_bridge.context import FlightContext
from geonav.mavlink_bridge.emulator import Emulator
from geonav.mavlink_bridge.ending import clear_autopilot_fence, end_action, record_result
from geonav.mavlink_bridge.flight import FlightConfig, ScriptedPolicy, path_actions
from geonav.mavlink_bridge.preflight import preflight
from geonav.mavlink_bridge.record import read_record
from geonav.mavlink_bridge.safety import (
    AutopilotFailsafe,
    OperatorTakeover,
    attribute_mode_change,
    failsafe_evidence,
)
from geonav.mavlink_bridge.signals import StopSignals
from geonav.mavlink_bridge.vehicle import VehicleState
from geonav.testing import textured_scene


@pytest.fixture(scope="module")
def scene() -> Any:
    return textured_scene(60.0, 0.5, towers=False)




def _context(scene: Any, emu: Emulator, out: Path, backend: str = "pymavlink",
             **cfg: Any) -> FlightContext:
    config = FlightConfig(target_cell=TARGET, start_cell=START, timeouts=FAST, **cfg)
    policy = ScriptedPolicy(path_actions(START, TARGET), META)
    return FlightContext.begin(open_vehicle(emu.connect_url, backend), scene, policy, config,
                               out)


def test_preflight_places_the_flight_and_moves_nothing(scene: Any, tmp_path: Path) -> None:
    with fast_emulator(scene, "px4") as emu:
        ctx = _context(scene, emu, tmp_path)
        try:
            preflight(ctx)
            assert ctx.planner is not None and ctx.fence is not None
            assert ctx.watchdog is not None and ctx.pump is not None and not ctx.pump.running
            assert ctx.start_cell == START and ctx.target_img.shape == (32, 32, 3)
            assert ctx.watchdog.gps_required  # a 3D fix before take-off: the fix is watched
            # nothing armed, nothing streamed; the autopilot holds the scene's fence
            assert not emu.armed and not emu.setpoints
            assert not emu.commands_named(M.MAV_CMD_COMPONENT_ARM_DISARM)
            assert len(emu.fence_items) == 4 and emu._params()["GF_ACTION"] == 5.0
            end = end_action(ctx, Verdict("refused", "test"))
            assert end.action == "none"  # geonav never armed: it commands nothing
            clear_autopilot_fence(ctx)
            assert emu.fence_items == [] and emu._params()["GF_ACTION"] == 2.0
        finally:
            ctx.rec.close()
            ctx.vehicle.close()


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_the_phases_in_order(scene: Any, tmp_path: Path, autopilot: str) -> None:
    with fast_emulator(scene, autopilot) as emu:
        ctx = _context(scene, emu, tmp_path)
        preflight(ctx)
        # Take-off and positioning: armed in the autonomy mode, at the altitude, over START.
        take_off_and_position(ctx)
        assert ctx.phase == "autonomy" and ctx.we_fly and ctx.cell == START
        assert emu.armed and emu.mode == M.AUTONOMY_MODE[autopilot]
        assert -emu.pos[2] == pytest.approx(10.0, abs=1.0)
        assert ctx.pump is not None and ctx.pump.running
        # The step loop: the scripted path, one record row per step.
        verdict = step_loop(ctx)
        assert verdict == Verdict("reached", f"target cell {TARGET} reached in 3 steps", True)
        assert ctx.steps == ctx.flown_steps == 3 and ctx.cell == TARGET
        # The end action: LAND confirmed on the heartbeat, disarmed; then the fence back.
        end = end_action(ctx, verdict)
        assert end.action == "land" and end.confirmed and end.disarmed and not emu.armed
        clear_autopilot_fence(ctx)
        assert emu.fence_items == []
        # The record: the result row is written before any picture is drawn.
        result = record_result(ctx, verdict, end, StopSignals())
        assert result.png_path is None and "track" not in result.summary()
        rows = read_record(result.record_path)
        assert rows[-1]["kind"] == "result" and rows[-1]["outcome"] == "reached"
        assert [r["step"] for r in rows if r["kind"] == "step"] == [1, 2, 3]
        assert result.draw_track() is not None and result.png_path.exists()


def _state(mode: str = "rtl", status: int = M.MAV_STATE_ACTIVE,
           texts: tuple[tuple[float, int, str], ...] = ()) -> VehicleState:
    return VehicleState(M.ARDUPILOT, status, mode, True, 0.1, LocalNED(0, 0, -10), (0, 0, 0),
                        0.1, None, None, recent_texts=texts)


def test_failsafe_evidence_is_the_status_or_the_autopilots_words() -> None:
    assert failsafe_evidence(_state()) == ""
    assert "CRITICAL" in failsafe_evidence(_state(status=M.MAV_STATE_CRITICAL))
    said = failsafe_evidence(_state(texts=((1.0, 2, "Battery 1 is critical 13.45V"),)))
    assert said == "autopilot says 'Battery 1 is critical 13.45V'"
    # a pre-arm complaint, or an old text, is no failsafe
    assert failsafe_evidence(_state(texts=((0.5, 2, "PreArm: GPS not healthy"),))) == ""
    assert failsafe_evidence(_state(texts=((30.0, 2, "Failsafe: battery"),))) == ""


class _Vehicle:
    def __init__(self, states: list[VehicleState]) -> None:
        self.states = states

    def state(self) -> VehicleState:
        if len(self.states) > 1:
            return self.states.pop(0)
        if not self.states:
            raise FlightError("gone")
        return self.states[0]


def test_a_mode_change_is_the_operators_unless_the_autopilot_says_otherwise() -> None:
    err = OperatorTakeover("operator takeover: mode changed to 'loiter'")
    quiet = attribute_mode_change(_Vehicle([_state("loiter")]), err, grace_s=0.2)
    assert quiet is err
    # the failsafe's text may come just after the heartbeat that shows the new mode
    later = [_state("rtl")] * 3 + [_state("rtl", texts=((0.1, 2, "Failsafe: GCS lost"),))]
    got = attribute_mode_change(_Vehicle(later), err, grace_s=2.0)
    assert isinstance(got, AutopilotFailsafe)
    assert str(got) == ("autopilot failsafe: mode changed to 'rtl' by the autopilot "
                        "(autopilot says 'Failsafe: GCS lost')")
    assert attribute_mode_change(_Vehicle([]), err) is err  # no link: as it was
