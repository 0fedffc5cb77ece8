"""Shared helpers with no project dependencies: locations, atomic output, strict JSON."""
