"""Frame sources for the flight loop: synthetic renders or a real camera through OpenCV.

``synthetic`` renders the nadir view from the scene at the position and
altitude the vehicle reports (SITL, dry runs); ``opencv:N`` (a device index)
or any URL OpenCV opens (``rtsp://...``) takes real frames, centre-cropped to
a square and resized with area averaging to the policy's input size.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import cv2
import numpy as np

from geonav.errors import ConfigError, FlightError
from geonav.geo import LocalNED, ScenePoint
from geonav.mavlink_bridge.vehicle import VehicleState


class FrameSource(Protocol):
    """Gives the policy's next image."""

    def frame(self, state: VehicleState) -> np.ndarray:
        """An (N, N, 3) uint8 RGB image."""

    def close(self) -> None:
        """Release the device."""


class SyntheticFrames:
    """Renders the view at the vehicle's reported position.

    Args:
        renderer: anything with ``render(x_m, y_m, alt_m, yaw_deg) -> (N, N, 3) uint8``
            (a :class:`geonav.camera.WarpRenderer`).
        to_scene: NED about the EKF origin -> (scene point, altitude above ground).
        yaw_deg: the fixed heading.
    """

    def __init__(
        self,
        renderer: object,
        to_scene: Callable[[LocalNED], tuple[ScenePoint, float]],
        yaw_deg: float = 0.0,
    ) -> None:
        self.renderer = renderer
        self.to_scene = to_scene
        self.yaw_deg = yaw_deg

    def frame(self, state: VehicleState) -> np.ndarray:
        if state.position is None:
            raise FlightError("no LOCAL_POSITION_NED to render a synthetic frame at")
        p, alt_m = self.to_scene(state.position)
        return self.renderer.render(p.x_m, p.y_m, max(alt_m, 1.0), self.yaw_deg)  # type: ignore[attr-defined]

    def close(self) -> None:
        pass


class OpenCVFrames:
    """Frames from ``cv2.VideoCapture`` (device index or URL), resized to ``size_px``."""

    def __init__(self, source: int | str, size_px: int) -> None:
        self.source = source
        self.size_px = size_px
        self.cap = cv2.VideoCapture(source)
        if not self.cap.isOpened():
            raise FlightError(f"cannot open camera {source!r} with OpenCV")

    def frame(self, state: VehicleState) -> np.ndarray:
        ok, bgr = self.cap.read()
        if not ok or bgr is None:
            raise FlightError(f"camera {self.source!r} returned no frame")
        return square_resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), self.size_px)

    def close(self) -> None:
        self.cap.release()


def square_resize(rgb: np.ndarray, size_px: int) -> np.ndarray:
    """Centre-crop to a square and resize with area averaging to ``size_px``."""
    h, w = rgb.shape[:2]
    side = min(h, w)
    y0, x0 = (h - side) // 2, (w - side) // 2
    crop = rgb[y0 : y0 + side, x0 : x0 + side]
    return cv2.resize(crop, (size_px, size_px), interpolation=cv2.INTER_AREA)


def parse_camera(spec: str) -> tuple[str, int | str | None]:
    """Camera spec -> (kind, device): ``synthetic``, ``opencv:0`` -> ("opencv", 0), URLs."""
    if spec == "synthetic":
        return "synthetic", None
    if spec.startswith("opencv:"):
        dev = spec.removeprefix("opencv:")
        return "opencv", int(dev) if dev.isdigit() else dev
    if "://" in spec:
        return "opencv", spec
    raise ConfigError(f"camera {spec!r}: use synthetic, opencv:DEVICE or an rtsp:// URL")
