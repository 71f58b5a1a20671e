"""geonav: learn drone visual navigation from aerial imagery and fly it over MAVLink.

Heavy dependencies (torch, rasterio, pymavlink, mavsdk, matplotlib, cv2) are imported
only by the modules that need them, so ``import geonav`` and ``geonav --help``
stay fast. Importing the package registers the Gymnasium env ``geonav/GeoNav-v0``
by its string entry point (the env module loads on the first ``gymnasium.make``).
"""

__version__ = "0.1.0"

ENV_ID = "geonav/GeoNav-v0"


def register_envs() -> None:
    """Register ``geonav/GeoNav-v0`` with Gymnasium (idempotent)."""
    from gymnasium.envs.registration import register, registry

    if ENV_ID not in registry:
        register(id=ENV_ID, entry_point="geonav.env:GeoNavEnv")


register_envs()
