"""geonav: learn drone visual navigation from aerial imagery and fly it over MAVLink.

The flow and its entry points (``geonav --help`` for the command line):

* imagery -> scene package: :func:`geonav.tiles.ingest.ingest` (GeoTIFF, XYZ tiles,
  MBTiles), :func:`geonav.tiles.ingest.ingest_synthetic`; :class:`geonav.scene.Scene`;
* scene -> navigation tasks: :func:`geonav.tasks.sample_meta_tasks`,
  :func:`geonav.tasks.whole_scene_tasks`, :class:`geonav.tasks.TaskSet`;
* tasks -> Gymnasium env: :class:`geonav.env.GeoNavEnv` (``geonav/GeoNav-v0``);
* training: :func:`geonav.policy.engine.build_trainer` (A3C, SAVN, ISAR, PPO on the
  default batched engine; ``.train()``), :func:`geonav.policy.engine.build_meta_trainer`,
  :func:`geonav.policy.curriculum.run_curriculum`;
* evaluation: :func:`geonav.policy.evaluation.evaluate_checkpoint` (beside chance,
  :mod:`geonav.difficulty`);
* experiments: :func:`geonav.experiments.runner.run_experiment` over a TOML config
  (:func:`geonav.experiments.config.load_config`);
* flight: :func:`geonav.mavlink_bridge.flight.fly` (PX4 or ArduPilot over MAVLink, or
  the built-in emulator).

Heavy dependencies (torch, rasterio, pymavlink, mavsdk, matplotlib, cv2) are imported
only by the modules that need them, so ``import geonav`` and ``geonav --help``
stay fast. Importing the package registers the Gymnasium env ``geonav/GeoNav-v0``
by its string entry point (the env module loads on the first ``gymnasium.make``).
"""

__version__ = "0.1.0"


def _quiet_interrupt_in_the_command() -> None:
    """In the ``geonav`` command only: Ctrl-C while the package is still importing (before
    :func:`geonav.cli.main` can catch it) prints one line instead of a traceback; Python
    still exits as killed by SIGINT."""
    import os
    import sys

    if not sys.argv or os.path.basename(sys.argv[0]) != "geonav":
        return
    previous = sys.excepthook

    def hook(kind, value, tb):  # type: ignore[no-untyped-def]
        if issubclass(kind, KeyboardInterrupt):
            print("geonav: interrupted", file=sys.stderr)
        else:
            previous(kind, value, tb)

    sys.excepthook = hook


_quiet_interrupt_in_the_command()

ENV_ID = "geonav/GeoNav-v0"


def register_envs() -> None:
    """Register ``geonav/GeoNav-v0`` with Gymnasium (idempotent)."""
    from gymnasium.envs.registration import register, registry

    if ENV_ID not in registry:
        register(id=ENV_ID, entry_point="geonav.env:GeoNavEnv")


register_envs()
