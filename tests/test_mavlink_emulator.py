"""The emulator reproduces the autopilot behaviour the bridge relies on; CLI wiring."""

from __future__ import annotations

import argparse
import ctypes
import socket
import threading
import time

import pytest

from geonav.errors import CheckpointError, FlightError
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.backends import open_vehicle
from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig


def _vehicle(emu: Emulator):
    v = open_vehicle(emu.connect_url, "pymavlink")
    v.connect(5.0)
    return v


def test_ardupilot_streams_nothing_until_asked_and_undoes_boot_mode() -> None:
    cfg = EmulatorConfig(
        autopilot="ardupilot",
        time_scale=4,
        boot_s=2.0,
        origin_s=0.2,
        local_position_s=0.2,
        prearm_s=0.2,
    )
    with Emulator(cfg) as emu:
        v = _vehicle(emu)
        try:
            assert v.state().system_status == M.MAV_STATE_BOOT
            v.set_mode("guided", 2.0)  # ACCEPTED during boot ...
            time.sleep(0.8)
            assert v.state().position is None  # no default streams
            t0 = time.monotonic()
            while v.state().system_status != M.MAV_STATE_STANDBY and time.monotonic() - t0 < 3:
                time.sleep(0.05)
            time.sleep(0.4)
            assert v.state().mode == "stabilize"  # ... and undone when boot finished
            v.request_telemetry(10.0, 2.0)
            time.sleep(0.5)
            assert v.state().position is not None and v.state().origin is not None
        finally:
            v.close()


def test_px4_refuses_offboard_without_a_setpoint_stream() -> None:
    cfg = EmulatorConfig(
        autopilot="px4", time_scale=4, boot_s=0.1, origin_s=0.1, local_position_s=0.1, prearm_s=0.1
    )
    with Emulator(cfg) as emu:
        v = _vehicle(emu)
        try:
            time.sleep(0.3)
            assert (
                v.command(M.MAV_CMD_DO_SET_MODE, (1, 6, 0), 2.0)
                == M.MAV_RESULT_TEMPORARILY_REJECTED
            )
            from geonav.geo import LocalNED

            for _ in range(10):
                v.send_position_target(LocalNED(0, 0, -5), 0.0)
                time.sleep(0.05)
            assert v.command(M.MAV_CMD_DO_SET_MODE, (1, 6, 0), 2.0) == M.MAV_RESULT_ACCEPTED
            time.sleep(0.6)  # > COM_OF_LOSS_T (1 s emulated) without setpoints
            assert v.state().mode == "land"
            assert "offboard loss" in emu.mode_history()[-1]
        finally:
            v.close()


def test_fly_without_policy_package_is_a_clear_checkpoint_error(tmp_path) -> None:
    from geonav.mavlink_bridge import flight

    try:
        import geonav.policy.inference  # noqa: F401
    except ImportError:
        with pytest.raises(CheckpointError, match="PolicyRunner"):
            flight.load_policy(tmp_path / "missing.pt")
    else:
        with pytest.raises(Exception):  # noqa: B017 - a missing file must not load
            flight.load_policy(tmp_path / "missing.pt")


def test_cli_registers_fly_and_emulator() -> None:
    from geonav.mavlink_bridge import cli

    p = argparse.ArgumentParser()
    cli.add_parser(p.add_subparsers())
    a = p.parse_args(
        [
            "fly",
            "c.pt",
            "--scene",
            "s",
            "--target",
            "3,4",
            "--start",
            "1,2",
            "--backend",
            "mavsdk",
            "--end",
            "rtl",
            "--dry-run",
        ]
    )
    assert (a.target, a.start, a.backend, a.end, a.dry_run) == (
        (3, 4),
        (1, 2),
        "mavsdk",
        "rtl",
        True,
    )
    a = p.parse_args(
        ["emulator", "--autopilot", "ardupilot", "--listen", "udp:127.0.0.1:0", "--seconds", "0.3"]
    )
    assert a.handler(a) == 0


def _emulator_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "mavlink-emulator" and t.is_alive()]


def test_start_is_idempotent_one_thread_at_the_configured_rate() -> None:
    before = len(_emulator_threads())
    emu = Emulator(EmulatorConfig(time_scale=6.0)).start()
    with emu:  # a second start (the old tests did this) must not start a second thread
        emu.start()
        assert len(_emulator_threads()) == before + 1
        with emu._lock:
            t0, w0 = emu.t_s, time.monotonic()
        time.sleep(0.5)
        with emu._lock:
            t1, w1 = emu.t_s, time.monotonic()
        # Two threads sharing one vehicle ran the emulated clock at twice the rate.
        assert t1 - t0 <= 6.0 * (w1 - w0) * 1.05 + 0.2
        assert t1 - t0 > 0
    assert not emu.running and len(_emulator_threads()) == before  # stop() joined it
    emu.stop()  # twice is fine
    with pytest.raises(FlightError, match="stopped"):
        emu.start()


def test_a_frozen_process_pauses_the_emulated_vehicle() -> None:
    # libc usleep through ctypes.PyDLL keeps the GIL: every Python thread of the process
    # stands still for 1 s, as in a long garbage-collector pause.
    freeze = ctypes.PyDLL(None).usleep
    cfg = EmulatorConfig(time_scale=6.0)
    with Emulator(cfg) as emu:
        time.sleep(0.2)
        with emu._lock:
            n0 = emu.iterations
        freeze(1_000_000)
        deadline = time.monotonic() + 5.0
        while emu.iterations < n0 + 3 and time.monotonic() < deadline:
            time.sleep(0.001)
        with emu._lock:
            log = list(emu.steps_log)[-(emu.iterations - n0) :]
    gap_s, dt_s = max(log)  # the iteration that spanned the freeze
    assert gap_s >= 0.9, log[:5]
    # Emulated time of that iteration is bounded (0.12 s at 6x), not 6 s.
    assert dt_s < 1.5
    assert dt_s <= max(cfg.max_dt_s, 2 * 0.01 * cfg.time_scale) + 1e-9


def test_connect_retries_until_a_late_tcp_autopilot_listens() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = EmulatorConfig(autopilot="ardupilot", listen=f"tcp:127.0.0.1:{port}", boot_s=0.1)
    started: list[Emulator] = []
    timer = threading.Timer(1.0, lambda: started.append(Emulator(cfg).start()))
    timer.start()
    v = open_vehicle(f"tcp:127.0.0.1:{port}", "pymavlink")
    try:
        v.connect(10.0)  # "Connection refused" for the first second: retried
        assert v.autopilot == "ardupilot"
    finally:
        v.close()
        timer.join()
        for emu in started:
            emu.stop()


@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_both_backends_read_the_battery_and_the_fix_and_set_parameters(
        autopilot: str, backend: str) -> None:
    cfg = EmulatorConfig(autopilot=autopilot, time_scale=4, boot_s=0.1, origin_s=0.1,
                         local_position_s=0.1, prearm_s=0.1, battery_pct=63.0)
    with Emulator(cfg) as emu:
        v = open_vehicle(emu.connect_url, backend)
        v.connect(10.0)
        try:
            v.request_telemetry(10.0, 3.0)
            deadline = time.monotonic() + 5
            while (v.state().battery_pct is None or v.state().gps_fix_type != 3) and \
                    time.monotonic() < deadline:
                time.sleep(0.05)
            s = v.state()
            assert s.battery_pct == 63.0 and s.battery_v == pytest.approx(15.47, abs=0.01)
            assert s.gps_fix_type == 3
            emu.drain_battery(12.0)
            time.sleep(1.0)
            assert v.state().battery_pct == 12.0
            # parameters: an integer (PX4 sends its bytes in the float field) and a float
            name = "GF_ACTION" if autopilot == "px4" else "FENCE_ACTION"
            v.set_param(name, 3, True, 3.0)
            assert v.get_param(name, 3.0) == 3.0 and emu._params()[name] == 3.0
            ceiling = "GF_MAX_VER_DIST" if autopilot == "px4" else "FENCE_ALT_MAX"
            v.set_param(ceiling, 42.5, False, 3.0)
            assert emu._params()[ceiling] == 42.5
        finally:
            v.close()
