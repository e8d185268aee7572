"""clod-adapter: continuous level of detail (CLoD-GS, Cheng et al., ICLR 2026) for existing
3D Gaussian Splatting checkpoints."""

__version__ = "0.1.0"
