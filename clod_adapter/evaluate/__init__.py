"""Scoring a model: the quality-vs-time comparison against the peers, popping, metrics per level, the frontier, timing, LPIPS, storage."""
