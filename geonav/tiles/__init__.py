"""Ingestion: GeoTIFFs, XYZ tiles, MBTiles, tile downloads and synthetic scenes -> scene packages."""
