"""Scoring a model: the quality-vs-time comparison against the peers (``comparison``), popping,
metrics per level, the frontier, interleaved timing, LPIPS, storage."""
