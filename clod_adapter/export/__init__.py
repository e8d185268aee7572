"""Writing a model out: baked levels, video, figures, the web page (:mod:`.web`)."""
