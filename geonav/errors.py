"""The geonav error tree.

Every failure a user can act on has its own class under :class:`GeonavError`.
Messages name the offending value and say what to do; the CLI prints the
message on one line and exits non-zero.
"""

from __future__ import annotations


class GeonavError(Exception):
    """Base class of every error geonav raises on purpose."""


class GeoError(GeonavError):
    """A coordinate or CRS problem (unknown CRS, point outside the valid area)."""


class SceneError(GeonavError):
    """A scene package is missing, incomplete or inconsistent."""


class IngestError(GeonavError):
    """Source imagery or a surface model cannot be turned into a scene."""


class MissingCRS(IngestError):
    """A raster has no coordinate reference system."""


class NoOverlap(IngestError):
    """Two rasters (or a raster and a bbox) do not overlap."""


class TileError(IngestError):
    """XYZ/MBTiles/tile-download problems."""


class CameraError(GeonavError):
    """A camera setting or a render request is invalid."""


class TaskError(GeonavError):
    """A navigation task or task set is invalid (region, target, reachability)."""


class ConfigError(GeonavError):
    """A configuration value or option is invalid."""


class ReportError(GeonavError):
    """A run folder cannot be read into a report (a corrupt metrics file, a finished unit
    whose files are missing)."""


class TrainingDiverged(GeonavError):
    """A learner's losses became NaN or infinite: the run cannot go on from here."""


class CheckpointError(GeonavError):
    """A checkpoint is corrupt or does not match the environment it is used with."""


class FlightError(GeonavError):
    """Anything that stops a flight; the bridge lands or returns after it."""


class FlightTimeout(FlightError):
    """A gated flight phase did not see the telemetry it waits for in time."""


class CommandRejected(FlightError):
    """An autopilot answered a command with a COMMAND_ACK other than ACCEPTED."""


class SafetyViolation(FlightError):
    """A safety rule fired (geofence, watchdog, operator takeover)."""


class OutputError(GeonavError):
    """An output path cannot be written (it is not geonav's to replace, or is being written)."""


class OutputExists(OutputError):
    """The output exists and is not geonav's own output of that kind, or --force is missing."""


class OutputBusy(OutputError):
    """Another geonav process is writing the same output path."""


class MissingExtra(GeonavError):
    """An optional dependency is not installed; the message names the pip extra."""

    def __init__(self, package: str, extra: str, purpose: str) -> None:
        super().__init__(
            f"{purpose} needs the optional package {package!r}: "
            f"pip install 'geonav[{extra}]'"
        )
        self.package = package
        self.extra = extra


class GeonavWarning(UserWarning):
    """Something still works but loses data, accuracy or speed (coarse imagery, masked tiles)."""
