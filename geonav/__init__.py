"""geonav: learn drone visual navigation from aerial imagery and fly it over MAVLink.

Heavy dependencies (torch, rasterio, pymavlink, mavsdk, matplotlib) are imported
only by the modules that need them, so ``import geonav`` and ``geonav --help``
stay fast.
"""

__version__ = "0.1.0"
