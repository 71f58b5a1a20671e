"""Whether a scene suits what it will be flown at: coverage needs and their warnings.

:class:`CoverageNeeds` names the views and region tasks a run will use (default: the
paper's 84 px views down to 15 m and 150 m tasks with a 300 m view margin);
:func:`check_coverage` warns when the imagery is too coarse or too small for them,
:func:`mask_coverage` when much of the scene has no imagery.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from geonav.scene import Scene

#: Highest altitude (m) of the paper's protocol; its view sets the margin a task needs.
MAX_ALT_M = 300.0
#: Lowest altitude (m); its view sets the finest GSD the imagery should have.
MIN_ALT_M = 15.0
META_TASK_SIZE_M = 150.0

@dataclass(frozen=True)
class CoverageNeeds:
    """What a scene will be flown at, for ingestion's coverage warnings: a warning only
    for what the run will use (a config with 30 m tasks of 45 m is not warned about the
    paper's 15 m views or 150 m tasks at 300 m).

    Attributes:
        views: (altitude m, view side px, field of view deg) of every view the tasks use;
            the imagery should be fine enough for the lowest one.
        tasks: (task side m, altitude m of its view margin, fov deg) of every region task;
            the scene should hold the region with that view around it.
    """

    views: tuple[tuple[float, int, float], ...] = ((MIN_ALT_M, 84, 90.0),)
    tasks: tuple[tuple[float, float, float], ...] = ((META_TASK_SIZE_M, MAX_ALT_M, 90.0),)

    @classmethod
    def paper(cls) -> CoverageNeeds:
        """The paper's protocol (the default when nothing says otherwise): 84 px views
        down to 15 m, 150 m tasks with a 300 m view margin."""
        return cls()


def check_coverage(scene: Scene, needs: CoverageNeeds | None = None) -> list[str]:
    """Warnings for imagery too coarse for the lowest view ``needs`` names, or too small for
    its largest task with its view margin (default: the paper's 15 m views and 150 m tasks
    at 300 m)."""
    needs = needs or CoverageNeeds.paper()
    messages = []
    if needs.views:
        alt, px, fov = min(needs.views, key=lambda v: 2 * v[0] * math.tan(
            math.radians(v[2]) / 2) / v[1])
        need_gsd = 2 * alt * math.tan(math.radians(fov) / 2) / px
        if scene.gsd_m > need_gsd * 1.001:
            messages.append(
                f"imagery at {scene.gsd_m:.3f} m/px is {scene.gsd_m / need_gsd:.2f}x coarser "
                f"than the {need_gsd:.3f} m/px that {px} px views at {alt:g} m need; "
                "low-altitude views will be blurred")
    if needs.tasks:
        size, alt, fov = max(needs.tasks, key=lambda t: 2 * t[1] * math.tan(
            math.radians(t[2]) / 2) + t[0])
        need_m = 2 * alt * math.tan(math.radians(fov) / 2) + size
        side = min(scene.size_m)
        if side < need_m:
            messages.append(
                f"the scene is {side:.0f} m across, {need_m - side:.0f} m short of the "
                f"{need_m:.0f} m a {size:g} m task needs with its {alt:g} m view margin")
    return messages


def mask_coverage(mask: np.ndarray, bbox_lonlat: tuple | None,
                   rotated: bool = False) -> list[str]:
    # The grid hugs the sources, so a few percent of edge pixels can be empty after a
    # reprojection; more than that means missing tiles or a bbox reaching past the data.
    valid = float(mask.mean())
    if valid >= 0.95:
        return []
    if bbox_lonlat is not None:
        why = "the bbox reaches beyond the imagery, or tiles are missing or corrupt"
    elif rotated:
        why = "a source is rotated, so the north-up grid around it has empty corners"
    else:
        why = "missing or corrupt tiles, or gaps between sources"
    return [f"only {valid:.0%} of the scene has imagery ({why}); the rest is masked"]
