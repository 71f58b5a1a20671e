"""Picklable environment recipes for trainers, worker processes and experiment units."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any


@dataclass(frozen=True)
class EnvFactory:
    """A picklable recipe for the training/evaluation environment (one per worker).

    Attributes:
        scene_dir: scene package folder.
        tasks_file: task set JSON.
        alt_m: fly every task at this altitude (None: the tasks' own).
        obs_size_px: camera image side (None: the task set's camera).
        max_steps: episode cap override (None: the tasks' own).
        augment: imagery randomisation (:class:`geonav.augment.AugmentConfig`): the env is
            wrapped in :class:`geonav.wrappers.ImageryRandomisation`, whose tables the
            batched engine picks up; ``dataclasses.replace`` keeps it, so the
            curriculum's other altitudes get the same variants.
    """

    scene_dir: str
    tasks_file: str
    alt_m: float | None = None
    obs_size_px: int | None = None
    max_steps: int | None = None
    augment: Any = None

    def __call__(self) -> Any:
        from geonav.camera import Camera
        from geonav.env import GeoNavEnv
        from geonav.scene import Scene
        from geonav.tasks import TaskSet

        scene = Scene.open(self.scene_dir)
        ts = TaskSet.load(self.tasks_file)
        if self.alt_m is not None:
            ts = replace(ts, tasks=[t if t.alt_m == self.alt_m else t.with_alt(self.alt_m)
                                    for t in ts.tasks])
        camera = ts.camera if self.obs_size_px is None else Camera(self.obs_size_px,
                                                                   ts.camera.fov_deg)
        env = GeoNavEnv(scene, ts, camera=camera, max_steps=self.max_steps)
        if self.augment is None:
            return env
        from geonav.wrappers import ImageryRandomisation

        return ImageryRandomisation(env, self.augment)
