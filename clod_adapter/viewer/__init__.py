"""Interactive level-of-detail viewer (``clod-view``) on viser.

Core pieces (no viser needed, importable with the base install):

* :mod:`.model`: loading the model and its trained ``max_sv`` (:func:`model_max_sv`);
* :mod:`.cameras`: viser camera poses <-> our pinhole cameras, the start view;
* :mod:`.selection`: what one client camera is sent at one level (:func:`view_payload`);
* :mod:`.raster_time`: the estimated CPU raster time for a drawn count.

:mod:`.app` (imports viser, the ``viewer`` extra) serves them: one LoD selection per connected
browser camera.
"""
from .cameras import camera_from_pose, default_start_view, pose_from_camera, scene_start_view
from .model import DEFAULT_MAX_SV, load_view_model, model_max_sv
from .selection import DEFAULT_MAX_DRAWN, BYTES_PER_GAUSSIAN, ViewPayload, covariances, view_colors, view_payload
from .raster_time import RasterTimeModel, calibrate_raster_time

__all__ = [
    "camera_from_pose", "pose_from_camera", "default_start_view", "scene_start_view",
    "DEFAULT_MAX_SV", "model_max_sv", "load_view_model",
    "DEFAULT_MAX_DRAWN", "BYTES_PER_GAUSSIAN", "ViewPayload", "view_payload", "covariances",
    "view_colors", "RasterTimeModel", "calibrate_raster_time",
]
