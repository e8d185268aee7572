"""The design studies behind the defaults (docs/studies.md), each ``python -m benchmarks.studies.NAME``."""
