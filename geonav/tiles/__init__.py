"""Ingestion: GeoTIFFs, XYZ tiles, MBTiles, tile downloads, synthetic scenes -> scene packages."""

#: Default memory budget (MiB) for the arrays one ingestion holds (``--memory-budget``).
DEFAULT_MEMORY_BUDGET_MB = 4096
#: The units ``--dsm-units`` accepts for DSM/DEM values.
DSM_UNIT_CHOICES = ("m", "ft", "us-ft")
