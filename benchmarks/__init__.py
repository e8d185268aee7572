"""The project's measurements: ``quality_vs_time`` (docs/results.md) and ``studies`` (docs/studies.md),
run from the repository root as modules (``python -m benchmarks.quality_vs_time --docs``);
``common`` holds what they share (inputs, cached adaptations, splits)."""
