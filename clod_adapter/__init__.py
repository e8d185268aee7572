"""clod-adapter: continuous level of detail (CLoD-GS, Cheng et al., ICLR 2026) for existing
3D Gaussian Splatting checkpoints.

The public API, importable from the package root (loaded on first use, so ``import
clod_adapter`` stays light and does not import torch: the CLIs set OpenMP defaults first):

* models: :class:`Gaussians`, :func:`load_model`, :func:`read_ply`, :func:`write_ply`,
  :class:`LodSettings`;
* scenes: :func:`load_scene`, :class:`Camera`, :class:`Scene`;
* rendering at a level of detail: :func:`render_lod`, :func:`lod_subset`, :func:`view_lod`,
  :class:`LodView`, :class:`Budget` (a count, a share, a cost or milliseconds instead of a
  level), :func:`clod_rasterization` (gsplat ``rasterization`` + LoD; its LoD arguments for a
  model: :func:`clod_kwargs`), :func:`rasterization` (gsplat-compatible, no LoD);
* adapting: :class:`AdaptConfig`, :func:`prepare`, :func:`fit` (the fine-tune), :class:`EtaGradient`;
* the three jobs behind the CLIs: :func:`run_adapt_job` (``clod-adapt``, options
  :class:`AdaptOptions`), :func:`evaluate_report` (``clod-eval``, options :class:`EvalOptions`),
  :func:`export_model` (``clod-export``, options :class:`ExportOptions`).
"""

__version__ = "0.1.0"

#: public name -> (module, attribute)
_EXPORTS = {
    "Gaussians": ("gaussians", "Gaussians"), "LodSettings": ("lod_settings", "LodSettings"),
    "load_model": ("io.load", "load_model"), "read_ply": ("io.ply", "read_ply"), "write_ply": ("io.ply", "write_ply"),
    "load_scene": ("io.load", "load_scene"), "Camera": ("io.scene", "Camera"), "Scene": ("io.scene", "Scene"),
    "render_lod": ("lod.draw", "render_lod"), "lod_subset": ("lod.draw", "lod_subset"),
    "Budget": ("lod.budget", "Budget"), "EtaGradient": ("lod_settings", "EtaGradient"),
    "view_lod": ("lod.draw", "view_lod"), "LodView": ("lod.draw", "LodView"),
    "clod_rasterization": ("lod.hook", "clod_rasterization"),
    "clod_kwargs": ("lod.hook", "clod_kwargs"),
    "rasterization": ("render", "rasterization"),
    "AdaptConfig": ("train.config", "AdaptConfig"), "prepare": ("train.loop", "prepare"), "fit": ("train.loop", "fit"),
    "run_adapt_job": ("jobs.adapt", "run"), "AdaptOptions": ("jobs.adapt", "AdaptOptions"),
    "evaluate_report": ("jobs.eval", "evaluate_report"), "EvalOptions": ("jobs.eval", "EvalOptions"),
    "export_model": ("jobs.export", "export"), "ExportOptions": ("jobs.export", "ExportOptions"),
}
__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str):
    where = _EXPORTS.get(name)
    if where is None:
        raise AttributeError(f"module 'clod_adapter' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"{__name__}.{where[0]}"), where[1])
    globals()[name] = value
    return value
