"""Writing a model out: baked levels, video, figures."""
