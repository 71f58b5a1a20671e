"""``geonav fly`` and ``geonav emulator`` / ``geonav mavlink emulate``.

Thin: parses arguments, calls :func:`geonav.mavlink_bridge.flight.fly` or the
emulator, and prints a one-line result (the CLI is the only place that prints).
``geonav fly`` exits with the flight's outcome code: 0 reached, 1 missed, 2 bad
input, 3 refused before arming, 4 link lost, 5 an operator took over (a mode change
by an RC pilot or a GCS), 6 safety stop (geonav landed: fence, obstacle, battery below
--min-battery, a stalled policy...), 7 autopilot failsafe (the autopilot changed the
mode itself: its battery, fence, GPS/EKF or link failsafe), 8 position lost (geonav
stopped commanding and left the vehicle to the autopilot's failsafe), 128 + N when
signal N (SIGINT 130, SIGHUP 129, SIGTERM 143) ended it.
"""

from __future__ import annotations

import argparse
import signal
import threading
from typing import Any

from geonav.cliutil import (
    altitude_m,
    finite_float,
    needs_subcommand,
    nonneg_float,
    positive_float,
    positive_int,
)
from geonav.errors import ConfigError


def _cell(text: str) -> tuple[int, int]:
    try:
        ix, iy = (int(v) for v in text.split(","))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"cell {text!r}: give IX,IY (east, north)") from err
    return ix, iy


def _lonlat(text: str) -> Any:
    from geonav.errors import GeoError
    from geonav.geo import LonLat

    parts = text.split(",")
    if len(parts) not in (2, 3):
        raise argparse.ArgumentTypeError(f"home {text!r}: give LAT,LON[,ALT]")
    lat, lon, *alt = (finite_float(v) for v in parts)
    try:
        return LonLat(lon, lat, alt[0] if alt else 0.0)
    except GeoError as err:
        raise argparse.ArgumentTypeError(f"home {text!r}: {err}") from None


def add_parser(subparsers: Any) -> None:
    """Register ``fly``, ``emulator`` and ``mavlink emulate``."""
    p = subparsers.add_parser("fly", help="fly a checkpoint on PX4/ArduPilot over MAVLink")
    _flight_args(p)
    _safety_args(p)
    p.set_defaults(handler=run_fly)

    for name in ("emulator",):
        e = subparsers.add_parser(name, help="run the MAVLink vehicle emulator (tests, dry runs)")
        _emulator_args(e)
    m = subparsers.add_parser("mavlink", help="MAVLink tools")
    m.set_defaults(handler=needs_subcommand(m))
    msub = m.add_subparsers(dest="mavlink_command", metavar="TOOL")
    _emulator_args(msub.add_parser("emulate", help="run the MAVLink vehicle emulator"))


def _flight_args(p: argparse.ArgumentParser) -> None:
    """What to fly, where, and how to connect."""
    p.add_argument("checkpoint", help="policy checkpoint (.pt)")
    p.add_argument("--scene", required=True, help="scene package folder")
    p.add_argument("--connect", help="udpin:0.0.0.0:14540, tcp:127.0.0.1:5760, /dev/ttyACM0:921600")
    p.add_argument("--backend", choices=("pymavlink", "mavsdk"), default="pymavlink")
    p.add_argument("--camera", default="synthetic", help="synthetic, opencv:0 or rtsp://...")
    p.add_argument("--start", type=_cell, help="start cell IX,IY (default: under take-off)")
    p.add_argument("--target", type=_cell,
                   help="target cell IX,IY: over the scene bounds, or in the --task lattice "
                   "(a task file's target_cell as is)")
    p.add_argument("--task", help="task file FILE[:NAME] (geonav tasks): region, step, "
                   "altitude, target, step budget and obstacle model")
    p.add_argument("--alt", type=altitude_m,
                   help="flight altitude above take-off, m (default: the policy's; required "
                   "for a policy trained at several altitudes)")
    p.add_argument("--end", choices=("land", "rtl"), default="land")
    p.add_argument("--dry-run", action="store_true", help="fly against an in-process emulator")
    p.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4",
                   help="emulator flavour for --dry-run")
    p.add_argument("--max-steps", type=positive_int,
                   help="step budget (default: the task's, or 70)")
    p.add_argument("--connect-timeout", type=positive_float, default=30.0,
                   help="seconds to wait for the autopilot (TCP/serial connects are retried)")
    p.add_argument("--set-origin", action="store_true",
                   help="send SET_GPS_GLOBAL_ORIGIN at the scene origin (GPS-less vehicles)")
    p.add_argument("--out", default="flight", help="folder for flight.jsonl and track.png")


def _safety_args(p: argparse.ArgumentParser) -> None:
    """Fences, battery, obstacles, taking over."""
    p.add_argument("--max-alt", type=altitude_m, default=120.0,
                   help="altitude ceiling, m; a higher --alt/policy altitude is clamped with "
                   "a warning")
    p.add_argument("--max-distance", type=positive_float, default=float("inf"),
                   help="geofence radius around home, metres")
    p.add_argument("--fence-margin", type=nonneg_float,
                   help="setpoints stay this far inside the scene, m (default: one lattice "
                   "step); the vehicle may overshoot half of it before the flight ends")
    p.add_argument("--no-autopilot-fence", dest="autopilot_fence", action="store_false",
                   help="do not give the autopilot the scene's fence (by default it gets "
                   "it, with --end as its breach action, and it is cleared after landing)")
    p.add_argument("--min-battery", type=_percent, default=25.0, metavar="PCT",
                   help="refuse to arm below this battery charge, and end the flight with "
                   "--end when it drops below it (default 25, above PX4's 15%% low and 7%% "
                   "critical levels; 0: off)")
    p.add_argument("--on-obstacle", choices=("stay", "end"), default="stay",
                   help="a move into a DSM obstacle cell: refuse and keep position (as the "
                   "env), or end")
    p.add_argument("--takeover-airborne", action="store_true",
                   help="accept a vehicle that is already armed and flying (its position and "
                   "altitude are the start); without it geonav refuses such a vehicle")


def _percent(text: str) -> float:
    value = nonneg_float(text)
    if value >= 100:
        raise argparse.ArgumentTypeError(f"{text!r} must be a percentage below 100")
    return value


def _emulator_args(e: argparse.ArgumentParser) -> None:
    e.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4")
    e.add_argument("--home", type=_lonlat, help="LAT,LON[,ALT] of home (default Rotterdam)")
    e.add_argument(
        "--listen",
        default="udp:127.0.0.1:14580",
        help="udp:HOST:PORT (reply to senders), tcp:HOST:PORT, or udpout:HOST:PORT",
    )
    e.add_argument("--time-scale", type=positive_float, default=1.0,
                   help="emulated seconds per second")
    e.add_argument("--seconds", type=nonneg_float, default=0.0,
                   help="stop after this long (0: Ctrl-C)")
    e.set_defaults(handler=run_emulator)


def run_fly(args: argparse.Namespace) -> int:
    """Handler of ``geonav fly``: one result line, exit code of the outcome."""
    from geonav.mavlink_bridge.flight import fly
    from geonav.mavlink_bridge.sequence import Timeouts

    if not args.dry_run and not args.connect:
        raise ConfigError("give --connect URL, or --dry-run to fly against the emulator")
    if args.target is None and args.task is None:
        raise ConfigError("give --target IX,IY or --task FILE[:NAME]")
    if args.connect and not args.dry_run:
        from geonav.mavlink_bridge.vehicle import parse_connection

        parse_connection(args.connect)  # a bad port is refused before anything loads
    try:
        from geonav.cliutil import progress_bar

        progress = progress_bar("fly")
    except ImportError:
        progress = None
    result = fly(
        args.checkpoint,
        args.scene,
        target_cell=args.target,
        task=args.task,
        connect=args.connect,
        backend=args.backend,
        camera=args.camera,
        start_cell=args.start,
        end=args.end,
        dry_run=args.dry_run,
        autopilot=args.autopilot,
        out_dir=args.out,
        progress=progress,
        max_steps=args.max_steps,
        max_distance_m=args.max_distance,
        fence_margin_m=args.fence_margin,
        set_origin=args.set_origin,
        alt_m=args.alt,
        max_alt_m=args.max_alt,
        on_obstacle=args.on_obstacle,
        takeover_airborne=args.takeover_airborne,
        min_battery_pct=args.min_battery,
        autopilot_fence=args.autopilot_fence,
        timeouts=Timeouts(connect_s=args.connect_timeout),
        plot=False,
    )
    # The outcome first (its notes, an altitude clamp, were logged once as warnings when
    # the plan was made); then the picture, which may take a while on a loaded machine.
    print(result.summary(), flush=True)
    png = result.draw_track()
    if png is not None:
        print(f"track {png}")
    return result.exit_code


def run_emulator(args: argparse.Namespace) -> int:
    """Handler of ``geonav emulator`` / ``geonav mavlink emulate``."""
    from geonav.mavlink_bridge.emulator import EmulatorConfig, run_standalone

    kw: dict[str, Any] = {
        "autopilot": args.autopilot,
        "listen": args.listen,
        "time_scale": args.time_scale,
    }
    if args.home is not None:
        kw["home"] = args.home
    cfg = EmulatorConfig(**kw)
    stop = threading.Event()
    if args.seconds > 0:
        threading.Timer(args.seconds, stop.set).start()

    def ready(emu: Any) -> None:
        print(
            f"{cfg.autopilot} emulator on {cfg.listen}: connect with {emu.connect_url} "
            f"(MAVSDK {emu.mavsdk_url}); Ctrl-C to stop",
            flush=True,
        )

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGHUP):
            old[sig] = signal.signal(sig, on_signal)
    try:
        run_standalone(cfg, stop, ready)
    except KeyboardInterrupt:
        stop.set()
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return 0
