"""GeoNavEnv: a Gymnasium environment for visual navigation over aerial imagery."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces

import geonav
from geonav.camera import Camera, SliceRenderer
from geonav.errors import ConfigError, TaskError
from geonav.scene import Scene, open_shared
from geonav.tasks import ACTION_MEANINGS, ACTION_MOVES, Cell, NavTask, TaskMap, TaskSet, bind

ENV_ID = geonav.ENV_ID


class GeoNavEnv(gym.Env[dict[str, np.ndarray], np.int64]):
    """Navigate a drone over aerial imagery to the place a target image shows.

    The drone flies at a fixed altitude over a lattice of cells (one task's
    region); its downward camera gives the current view, and the target is the
    view from the goal cell at the same altitude. Heading is fixed north-up, as
    in the paper.

    ## Action space
    ``Discrete(4)``: 0 forward (+y, north), 1 right (+x, east), 2 left (-x,
    west), 3 backward (-y, south); each moves one lattice step.

    ## Observation space
    ``Dict(image=Box(0, 255, (N, N, 3), uint8), target=Box(0, 255, (N, N, 3), uint8))``:
    the current nadir view and the target cell's view (N = camera ``size_px``).

    ## Rewards
    ``success_reward`` (+5) on entering the target cell; otherwise
    ``step_reward`` (-0.01) per step, plus ``collision_reward`` (default 0)
    when a move is refused.

    ## Starting state
    A task is drawn (``task_sampling``: "random" or "cycle"), then a start
    cell uniformly among the free cells from which the target is reachable
    within ``max_steps`` (BFS over free cells). ``reset(options=...)`` accepts
    ``{"task": index or name, "start_cell": (ix, iy)}``.

    ## Episode end
    Terminated on reaching the target; truncated after ``max_steps`` steps
    (the task's cap unless overridden). A move into an obstacle cell or out of
    the region leaves the drone in place and sets ``info["collided"]``.

    ## Info
    ``position_m`` (x, y scene metres), ``cell``, ``target_cell``,
    ``distance_m`` (shortest free path to the target, metres), ``shortest_path``
    (BFS steps from this episode's start, for SPL), ``collided``, ``success``,
    ``is_success`` (the same flag under the name Stable-Baselines3 reads for
    ``rollout/success_rate`` and ``EvalCallback``), ``task``, ``task_index``,
    ``task_key`` (a hash of the scene, the task and the camera: names the task's views
    in caches that several envs share), ``alt_m``, ``steps``.

    ## Memory and pickling
    Observations are read-only slices of one prefiltered map per altitude
    (:class:`geonav.camera.SliceRenderer`), shared by every env of a process over
    the same scene; an env keeps no per-cell cache. A scene opened from a package
    is memory-mapped and pickles as its path, so an env pickles as the package
    path, its bound tasks and its parameters (a few kB), and vector-env workers
    map the same pages instead of copying the scene. An in-memory scene
    (:meth:`Scene.from_arrays`) pickles with its arrays.

    ## Version history
    * v0: initial version. Later additions that change no observation, reward or
      dynamics (so the version stays v0): ``info["is_success"]``; registration on
      ``import geonav``; light pickles and shared, memory-mapped render maps.

    Args:
        scene: a :class:`Scene` or the path of a scene package.
        tasks: a :class:`TaskSet`, a path to its JSON, one :class:`NavTask` or a list.
        camera: the camera (default: the task set's, else 84 px / 90 degrees).
        max_steps: override every task's episode cap.
        success_reward: reward on reaching the target.
        step_reward: reward per step otherwise.
        collision_reward: extra reward when a move is refused.
        task_sampling: "random" (uniform from ``np_random``) or "cycle" (in order).
        render_mode: None or "rgb_array".
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        scene: Scene | str | os.PathLike[str],
        tasks: TaskSet | NavTask | Sequence[NavTask] | str | os.PathLike[str],
        *,
        camera: Camera | None = None,
        max_steps: int | None = None,
        success_reward: float = 5.0,
        step_reward: float = -0.01,
        collision_reward: float = 0.0,
        task_sampling: str = "random",
        render_mode: str | None = None,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ConfigError(f"render_mode {render_mode!r} is not supported; use 'rgb_array'")
        if task_sampling not in ("random", "cycle"):
            raise ConfigError(f"task_sampling must be 'random' or 'cycle', not {task_sampling!r}")
        if max_steps is not None and max_steps < 1:
            raise ConfigError(f"max_steps must be >= 1, got {max_steps}")
        self.scene = scene if isinstance(scene, Scene) else open_shared(scene)
        if isinstance(tasks, (str, Path, os.PathLike)):
            tasks = TaskSet.load(tasks)
        if isinstance(tasks, TaskSet):
            tasks.check_scene(self.scene)
            self.camera = camera or tasks.camera
            task_list = list(tasks.tasks)
        else:
            self.camera = camera or Camera()
            task_list = [tasks] if isinstance(tasks, NavTask) else list(tasks)
        if not task_list:
            raise TaskError("GeoNavEnv needs at least one task")
        self.task_maps: list[TaskMap] = [bind(t, self.scene, self.camera) for t in task_list]
        # what names a task's views in caches shared across envs (the frozen encoder's)
        cam = json.dumps([self.camera.size_px, self.camera.fov_deg])
        self._task_keys = [
            f"{self.scene.identity}:" + hashlib.sha256(
                (cam + json.dumps(t.to_dict(), sort_keys=True)).encode()).hexdigest()[:16]
            for t in task_list]
        self.max_steps_override = max_steps
        self.success_reward = float(success_reward)
        self.step_reward = float(step_reward)
        self.collision_reward = float(collision_reward)
        self.task_sampling = task_sampling
        self.render_mode = render_mode
        self.renderer = SliceRenderer(self.scene, self.camera)
        n = self.camera.size_px
        self.observation_space = self._observation_space()
        self.action_space = spaces.Discrete(len(ACTION_MOVES))
        self.action_meanings = ACTION_MEANINGS
        self._starts: list[list[Cell] | None] = [None] * len(self.task_maps)
        self._views: list[dict[Cell, np.ndarray]] = [{} for _ in self.task_maps]
        self._cycle = -1
        self._tm: TaskMap = self.task_maps[0]
        self._ti = 0
        self._cell: Cell = (0, 0)
        self._start: Cell = (0, 0)
        self._steps = 0
        self._track: list[Cell] = []
        self._target_obs = np.zeros((n, n, 3), np.uint8)

    # -- observations and pickling -------------------------------------------------------
    def observation_at(self, task_index: int, cell: Cell) -> np.ndarray:
        """The (N, N, 3) uint8 view at a cell of a task (a new array)."""
        return self._view(task_index, cell).copy()

    def _view(self, task_index: int, cell: Cell) -> np.ndarray:
        """The same view as a read-only slice of the shared altitude map (no copy).

        The slices are kept per cell (an array header each, not the pixels), so a step
        costs a dict look-up as the old per-cell pixel cache did.
        """
        views = self._views[task_index]
        view = views.get(cell)
        if view is None:
            tm = self.task_maps[task_index]
            p = tm.lattice.center(cell)
            view = views[cell] = self.renderer.view(p.x_m, p.y_m, tm.task.alt_m)
        return view

    def _observation_space(self) -> spaces.Dict:
        n = self.camera.size_px
        image_space = spaces.Box(0, 255, (n, n, 3), np.uint8)
        return spaces.Dict({"image": image_space, "target": image_space})

    def __getstate__(self) -> dict[str, Any]:
        # what can be rebuilt from the scene and the camera is left out: the renderer and
        # the per-cell slices (references into the scene's shared maps), the target view
        # and the Box spaces (their bounds are two arrays of the image's size each)
        state = self.__dict__.copy()
        for key in ("renderer", "_views", "_target_obs", "observation_space"):
            state.pop(key, None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.renderer = SliceRenderer(self.scene, self.camera)
        self._views = [{} for _ in self.task_maps]
        self.observation_space = self._observation_space()
        self._target_obs = self.observation_at(self._ti, self._tm.task.target_cell)

    def task_key(self, task_index: int) -> str:
        """A task's ``info["task_key"]``: a hash of its scene, definition and camera."""
        return self._task_keys[task_index]

    def max_steps_of(self, task_index: int) -> int:
        return self.max_steps_override or self.task_maps[task_index].task.max_steps

    def start_cells(self, task_index: int) -> list[Cell]:
        starts = self._starts[task_index]
        if starts is None:
            starts = self._starts[task_index] = self.task_maps[task_index].start_cells(
                self.max_steps_of(task_index))
            if not starts:
                raise TaskError(f"task {self.task_maps[task_index].task.name!r} has no start "
                                f"cell within {self.max_steps_of(task_index)} steps of its target")
        return starts

    @property
    def task(self) -> NavTask:
        """The current episode's task."""
        return self._tm.task

    @property
    def task_index(self) -> int:
        return self._ti

    @property
    def tasks(self) -> list[NavTask]:
        return [tm.task for tm in self.task_maps]

    # -- Gymnasium API ------------------------------------------------------------------
    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict]:
        super().reset(seed=seed)
        options = options or {}
        ti = self._choose_task(options.get("task"))
        self._ti, self._tm = ti, self.task_maps[ti]
        starts = self.start_cells(ti)
        if options.get("start_cell") is not None:
            start = (int(options["start_cell"][0]), int(options["start_cell"][1]))
            if not self._tm.lattice.contains(start) or self._tm.blocked[start]:
                raise TaskError(f"start cell {start} is outside the lattice or blocked")
            if self._tm.dist_to_target[start] < 0:
                raise TaskError(f"the target is unreachable from start cell {start}")
        else:
            start = starts[int(self.np_random.integers(len(starts)))]
        self._start = self._cell = start
        self._steps = 0
        self._track = [start]
        self._target_obs = self.observation_at(ti, self._tm.task.target_cell)
        return self._observation(), self._info(collided=False)

    def _choose_task(self, requested: Any) -> int:
        if requested is not None:
            if isinstance(requested, str):
                names = [tm.task.name for tm in self.task_maps]
                if requested not in names:
                    raise TaskError(f"unknown task {requested!r}; tasks are {names}")
                return names.index(requested)
            index = int(requested)
            if not 0 <= index < len(self.task_maps):
                raise TaskError(f"task index {index} out of range 0..{len(self.task_maps) - 1}")
            return index
        if self.task_sampling == "cycle":
            self._cycle = (self._cycle + 1) % len(self.task_maps)
            return self._cycle
        return int(self.np_random.integers(len(self.task_maps)))

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict]:
        a = int(action)
        if not 0 <= a < len(ACTION_MOVES):
            raise ValueError(f"action {action!r} is not in Discrete({len(ACTION_MOVES)})")
        dx, dy = ACTION_MOVES[a]
        nxt = (self._cell[0] + dx, self._cell[1] + dy)
        tm = self._tm
        collided = not tm.lattice.contains(nxt) or bool(tm.blocked[nxt])
        if not collided:
            self._cell = nxt
        self._steps += 1
        self._track.append(self._cell)
        terminated = self._cell == tm.task.target_cell
        if terminated:
            reward = self.success_reward
        else:
            reward = self.step_reward + (self.collision_reward if collided else 0.0)
        truncated = not terminated and self._steps >= self.max_steps_of(self._ti)
        return self._observation(), reward, terminated, truncated, self._info(collided)

    def _observation(self) -> dict[str, np.ndarray]:
        return {"image": self._view(self._ti, self._cell).copy(),
                "target": self._target_obs.copy()}

    def _info(self, collided: bool) -> dict[str, Any]:
        tm = self._tm
        p = tm.lattice.center(self._cell)
        d = int(tm.dist_to_target[self._cell])
        success = self._cell == tm.task.target_cell
        return {
            "position_m": (p.x_m, p.y_m),
            "cell": self._cell,
            "target_cell": tm.task.target_cell,
            "distance_m": d * tm.task.step_m,
            "shortest_path": int(tm.dist_to_target[self._start]),
            "collided": collided,
            "success": success,
            "is_success": success,
            "task": tm.task.name,
            "task_index": self._ti,
            "task_key": self._task_keys[self._ti],
            "alt_m": tm.task.alt_m,
            "steps": self._steps,
        }

    def render(self) -> np.ndarray | None:
        """rgb_array: the view, the target and a map of the region with the track."""
        if self.render_mode != "rgb_array":
            return None
        side = 168
        view = cv2.resize(self._view(self._ti, self._cell), (side, side),
                          interpolation=cv2.INTER_NEAREST)
        target = cv2.resize(self._target_obs, (side, side), interpolation=cv2.INTER_NEAREST)
        cv2.rectangle(target, (0, 0), (side - 1, side - 1), (255, 60, 60), 2)
        return np.concatenate([view, target, self._minimap(side)], axis=1)

    def _minimap(self, side: int) -> np.ndarray:
        tm = self._tm
        nx, ny = tm.lattice.shape
        region = tm.task.region_m
        rs, cs = self.scene.window(region)
        base = self.scene.rgb[rs, cs]
        img = cv2.resize(base, (side, side), interpolation=cv2.INTER_AREA) if base.size else \
            np.zeros((side, side, 3), np.uint8)
        img = (img * 0.7).astype(np.uint8)

        def px(cell: Cell) -> tuple[int, int]:
            return (int((cell[0] + 0.5) / nx * side), int((ny - cell[1] - 0.5) / ny * side))

        r = max(1, side // (2 * max(nx, ny)))
        for cell in map(tuple, np.argwhere(tm.blocked)):
            cv2.circle(img, px((int(cell[0]), int(cell[1]))), r, (90, 90, 90), -1)
        pts = np.array([px(c) for c in self._track], np.int32)
        if len(pts) > 1:
            cv2.polylines(img, [pts], False, (255, 255, 0), 1)
        cv2.circle(img, px(tm.task.target_cell), r + 2, (255, 60, 60), -1)
        cv2.circle(img, px(self._cell), r + 1, (60, 255, 60), -1)
        return img


def register() -> None:
    """Register ``geonav/GeoNav-v0`` with Gymnasium (idempotent; ``import geonav`` does it)."""
    geonav.register_envs()
