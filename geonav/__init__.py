"""geonav."""
