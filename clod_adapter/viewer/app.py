"""The ``clod-view`` web viewer on viser (needs the ``viewer`` extra: ``pip install -e ".[viewer]"``).

Each connected browser gets its own panel and its own copy of the model's splats: on every
camera move (throttled to one update per ``throttle_s``) and on every control change, the
selection for *that* client camera is recomputed (:func:`clod_adapter.viewer.selection.view_payload`,
i.e. :func:`clod_adapter.lod.draw.lod_subset`: frustum, d', the LoD rule or the budget solver),
coloured by the SH at that camera and sent as one splat buffer (``n x 32`` bytes).

Controls: the level (``s_v`` slider from 1 to 2 x the trained ``max_sv``, further with a parent
tier, or a budget in % of the model), "compare: static opacity cut" (the pretrained-style cut at the same count, shown
instead of the LoD level), a scene-camera dropdown when cameras are given, and a read-out of the
Gaussians drawn, their share of the model, the ``s_v`` drawn and our CPU rasteriser's estimated
time for that count. The read-out is an HTML element ``#clod-readout`` whose ``data-*``
attributes carry the exact numbers (for scripts and tests).
"""
from __future__ import annotations

import html
import math
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from clod_adapter.lod.draw import tier_reach
from clod_adapter.gaussians import Gaussians
from clod_adapter.io.scene import Camera

from .cameras import ViewPose, camera_from_pose, default_start_view, scene_start_view
from .model import DEFAULT_MAX_SV
from ..lod.budget import Budget
from .selection import (DEFAULT_MAX_DRAWN, METHOD_ALL, METHOD_STATIC, ViewPayload, view_payload)
from .raster_time import RasterTimeModel, calibrate_raster_time

__all__ = ["LodViewer", "ViewRecord", "require_viser"]

MODE_SV = "s_v"
MODE_BUDGET = "budget (% of model)"
#: image size of the raster-time estimate when no scene camera gives one
DEFAULT_TIMING_SIZE = (640, 480)


def require_viser():
    """Import viser, or raise ImportError with the install line."""
    try:
        import viser  # noqa: F401
    except ImportError as e:
        raise ImportError('clod-view needs viser: pip install -e ".[viewer]"') from e
    return viser


@dataclass
class ViewRecord:
    """What was last sent to one client: the camera it was computed for, the payload, the
    settings, a counter (1 for the first update) and the wall time of the update (s)."""

    camera: Camera
    payload: ViewPayload
    settings: dict
    version: int
    update_s: float


class _Session:
    """One browser: its panel, its splats, its update thread."""

    def __init__(self, viewer: "LodViewer", client) -> None:
        self.viewer = viewer
        self.client = client
        self.dirty = threading.Event()
        self.stop = threading.Event()
        self.splats = None
        self.record: Optional[ViewRecord] = None
        self._build_gui()
        client.camera.on_update(lambda _cam: self.dirty.set())
        self.thread = threading.Thread(target=self._run, name=f"clod-view-client-{client.client_id}",
                                       daemon=True)
        self.dirty.set()
        self.thread.start()

    # --- panel ----------------------------------------------------------------------------
    def _build_gui(self) -> None:
        v, gui = self.viewer, self.client.gui
        lod = v.gaussians.sigma_d is not None
        with gui.add_folder("Level of detail"):
            self.mode = gui.add_dropdown("level by", (MODE_SV, MODE_BUDGET), initial_value=MODE_SV,
                                         disabled=not lod,
                                         hint="s_v: virtual distance scale (CLoD-GS Eq. 2); budget: "
                                              "at most this share of the model, s_v solved per view")
            self.sv = gui.add_slider("s_v", min=1.0, max=v.sv_max, step=0.05, initial_value=1.0,
                                     disabled=not lod,
                                     hint=f"1 = full detail; the model was trained up to {v.max_sv:g}")
            self.budget = gui.add_slider("budget %", min=0.1, max=100.0, step=0.1, initial_value=50.0,
                                         disabled=True,
                                         hint="at most this % of the model's Gaussians (a cap at the s_v = 1 level)")
            self.compare = gui.add_checkbox("compare: static opacity cut", initial_value=False,
                                            disabled=not lod,
                                            hint="show instead the k most opaque Gaussians in view with their "
                                                 "original opacities (a pretrained-style cut), k = the LoD count")
            self.readout = gui.add_html(_readout_html(None, None, None))
            self.note = gui.add_markdown(v.model_note, visible=bool(v.model_note))
        self.camera_dd = None
        if v.scene_cameras:
            names = tuple(name for name, _ in v.scene_cameras)
            self.camera_dd = gui.add_dropdown("scene camera", names, initial_value=names[0],
                                              hint="move to a view of the scene (--images)")
            self.camera_dd.on_update(lambda _e: self._go_to_camera(self.camera_dd.value))

        def on_mode(_e) -> None:
            by_sv = self.mode.value == MODE_SV
            self.sv.disabled = not by_sv
            self.budget.disabled = by_sv
            self.dirty.set()

        self.mode.on_update(on_mode)
        for h in (self.sv, self.budget, self.compare):
            h.on_update(lambda _e: self.dirty.set())

    def _go_to_camera(self, name: str) -> None:
        cams = dict(self.viewer.scene_cameras)
        if name not in cams:
            return
        pose = scene_start_view(cams[name], self.viewer.gaussians)
        apply_pose(self.client.camera, pose, self.client)

    # --- updates --------------------------------------------------------------------------
    def settings(self) -> dict:
        lod = self.viewer.gaussians.sigma_d is not None
        if not lod:
            return {}
        s = {"compare": bool(self.compare.value)}
        if self.mode.value == MODE_SV:
            s["s_v"] = float(self.sv.value)
        else:
            s["budget"] = Budget(share=min(float(self.budget.value) / 100.0, 1.0))
        return s

    def _run(self) -> None:
        while not self.stop.is_set():
            if not self.dirty.wait(0.25):
                continue
            self.dirty.clear()
            try:
                self.update()
            except Exception:  # keep serving; the panel says what went wrong
                msg = traceback.format_exc(limit=2).strip().splitlines()[-1]
                try:
                    self.readout.content = (f'<div id="clod-readout" data-error="1">update failed: '
                                            f'{html.escape(msg)}</div>')
                except Exception:
                    pass
            self.stop.wait(self.viewer.throttle_s)

    def update(self) -> ViewRecord:
        """Recompute and send the selection for this client's current camera."""
        v, cam = self.viewer, self.client.camera
        t0 = time.perf_counter()
        camera = camera_from_pose(cam.wxyz, cam.position, cam.fov, max(int(cam.image_width), 1),
                                  max(int(cam.image_height), 1))
        settings = self.settings()
        payload = view_payload(v.gaussians, camera, max_drawn=v.max_drawn, **settings)
        with self.client.atomic():
            if payload.n_drawn == 0:
                if self.splats is not None:
                    self.splats.visible = False
            elif self.splats is None:
                self.splats = self.client.scene.add_gaussian_splats(
                    "/clod_model", centers=payload.means, covariances=payload.covariances,
                    rgbs=np.clip(payload.rgbs, 0.0, 1.0), opacities=payload.opacities)
            else:
                self.splats.set_gaussians(payload.means, payload.covariances,
                                          np.clip(payload.rgbs, 0.0, 1.0), payload.opacities)
                self.splats.visible = True
            self.readout.content = _readout_html(payload, v.timer, v.timer_state)
        rec = ViewRecord(camera, payload, settings, (self.record.version + 1) if self.record else 1,
                         time.perf_counter() - t0)
        with v._cond:
            self.record = rec
            v._cond.notify_all()
        return rec

    def close(self) -> None:
        self.stop.set()
        self.dirty.set()

    @staticmethod
    def dom_id(handle) -> str:
        """The HTML ``id`` of a GUI control in the browser page (viser uses its uuid)."""
        return handle._impl.uuid


def apply_pose(camera_handle, pose: ViewPose, client=None) -> None:
    """Move a viser client camera to ``pose`` (position, orientation, vertical fov, orbit centre)."""
    import contextlib

    ctx = client.atomic() if client is not None else contextlib.nullcontext()
    with ctx:
        camera_handle.fov = float(pose.fov)
        camera_handle.position = pose.position
        camera_handle.look_at = pose.look_at
        camera_handle.up_direction = pose.up


def _fmt_bytes(n: int) -> str:
    for unit, div in (("GB", 1e9), ("MB", 1e6), ("KB", 1e3)):
        if n >= div:
            return f"{n / div:.1f} {unit}"
    return f"{n} B"


def _readout_html(p: Optional[ViewPayload], timer: Optional[RasterTimeModel], timer_state: Optional[str]) -> str:
    if p is None:
        return '<div id="clod-readout" data-drawn="">waiting for the camera ...</div>'
    sv = "" if p.s_v is None else repr(float(p.s_v))
    attrs = (f'data-drawn="{p.n_drawn}" data-total="{p.n_total}" data-in-view="{p.n_in_view}" '
             f'data-level="{p.n_level}" data-sv="{sv}" data-method="{p.method}" '
             f'data-capped="{int(p.capped)}"')
    lines = [f"<b>{p.n_drawn:,}</b> Gaussians drawn: <b>{100.0 * p.n_drawn / max(p.n_total, 1):.1f} %</b> "
             f"of the model ({p.n_total:,}; {p.n_in_view:,} in view)"]
    if p.method == METHOD_ALL:
        lines.append("no LoD (no sigma_d): every Gaussian in view")
    else:
        lines.append(f"s_v = {p.s_v:.2f}" + (" &middot; showing: <b>static opacity cut</b> at this count "
                                              "(most opaque in view, original opacities)"
                                              if p.method == METHOD_STATIC else " &middot; showing: CLoD level"))
    if timer is not None:
        lines.append(f"est. CPU raster ms: <b>{timer.estimate_ms(p.n_drawn):.1f}</b> "
                     f'<span style="opacity:0.7">({html.escape(timer.label())})</span>')
    else:
        lines.append(f"est. CPU raster ms: {html.escape(timer_state or 'n/a')}")
    lines.append(f"update: {_fmt_bytes(p.message_bytes)} ({p.n_drawn:,} x 32 B)")
    if p.capped:
        lines.append(f'<span style="color:#c92a2a">capped: the level selects {p.n_level:,} '
                     f"({_fmt_bytes(32 * p.n_level)} per update); sending {p.n_drawn:,} chosen by the "
                     + ("budget solver" if p.method != METHOD_ALL else "opacity") + "</span>")
    return (f'<div id="clod-readout" {attrs} style="font-size:0.8em;line-height:1.5">'
            + "<br>".join(lines) + "</div>")


class LodViewer:
    """A viser server showing one model at a level of detail chosen per browser camera.

    Args:
        gaussians: the model (CPU); with ``sigma_d`` for LoD, without it every Gaussian in view.
        max_sv: the trained maximum ``s_v`` (:func:`clod_adapter.viewer.model.model_max_sv`); the
            slider runs from 1 to ``2 * max_sv`` (a model with a parent tier: to where its parents
            are drawn at ``2 * max_sv``: ``2 max_sv`` times :func:`clod_adapter.lod.draw.tier_reach`).
        scene_cameras: ``(name, camera)`` pairs for the camera dropdown; the first is the start
            view. Empty: the start view is outside the model's bounding box
            (:func:`clod_adapter.viewer.cameras.default_start_view`).
        background: RGB in [0, 1] behind the splats.
        max_drawn: cap on the Gaussians sent per update (above it: budget-solved subset).
        throttle_s: at most one update per client per this many seconds.
        calibrate: time our CPU rasteriser on the model at startup (in a background thread) for
            the read-out's estimate.
        title: panel label.
    """

    def __init__(self, gaussians: Gaussians, *, max_sv: float = DEFAULT_MAX_SV,
                 scene_cameras: Sequence[tuple[str, object]] = (), background=(0.0, 0.0, 0.0),
                 max_drawn: int = DEFAULT_MAX_DRAWN, throttle_s: float = 0.1, calibrate: bool = True,
                 title: str = "clod-view") -> None:
        if not (max_sv >= 1.0 and math.isfinite(max_sv)):
            raise ValueError(f"max_sv must be a finite number >= 1, got {max_sv}")
        if max_drawn < 1:
            raise ValueError(f"max_drawn must be >= 1, got {max_drawn}")
        self.gaussians = gaussians.detach().to("cpu")
        self.max_sv = float(max_sv)
        st = self.gaussians.lod
        self.sv_max = round(2.0 * self.max_sv * tier_reach(self.gaussians), 2)  # tiers: to the last one's 2 max_sv
        self.scene_cameras = list(scene_cameras)
        self.background = tuple(float(c) for c in background)
        self.max_drawn = int(max_drawn)
        self.throttle_s = float(throttle_s)
        self.calibrate = calibrate
        self.title = title
        self.model_note = ("" if self.gaussians.sigma_d is not None else
                           "**No level of detail:** this model has no `sigma_d` (a plain 3DGS .ply), so "
                           "the level controls are disabled and every Gaussian in view is drawn. "
                           "`clod-adapt` gives it one.")
        if self.scene_cameras:
            self.start_pose = scene_start_view(self.scene_cameras[0][1], self.gaussians)
            c0 = self.scene_cameras[0][1]
            self.timing_camera = camera_from_pose(self.start_pose.wxyz, self.start_pose.position,
                                                  self.start_pose.fov, c0.width, c0.height)
        else:
            self.start_pose = default_start_view(self.gaussians)
            self.timing_camera = camera_from_pose(self.start_pose.wxyz, self.start_pose.position,
                                                  self.start_pose.fov, *DEFAULT_TIMING_SIZE)
        self.timer: Optional[RasterTimeModel] = None
        self.timer_state: Optional[str] = "timing our rasteriser ..." if calibrate else "not measured"
        self.server = None
        self._sessions: dict[int, _Session] = {}
        self._cond = threading.Condition()

    # --- lifecycle ------------------------------------------------------------------------
    def start(self, host: str = "127.0.0.1", port: int = 8080, verbose: bool = False) -> int:
        """Start serving on ``host:port`` (0: any free port; viser moves on to the next free
        port when ``port`` is taken). Returns the port bound."""
        viser = require_viser()
        if self.calibrate:
            self._prepare_rasteriser()
        self.server = server = viser.ViserServer(host=host, port=port, label=self.title, verbose=verbose)
        server.gui.configure_theme(show_share_button=False, control_width="medium")
        bg = np.full((2, 2, 3), np.round(np.clip(self.background, 0, 1) * 255), dtype=np.uint8)
        server.scene.set_background_image(bg, format="png")
        p = self.start_pose
        lo_hi = np.ptp(np.asarray(self.gaussians.means), axis=0)
        far = float(max(1000.0, 10.0 * np.linalg.norm(lo_hi) + np.linalg.norm(p.position)))
        server.scene.set_up_direction(tuple(float(x) for x in p.up))
        ic = server.initial_camera
        ic.fov, ic.far = float(p.fov), far
        ic.position, ic.look_at, ic.up = p.position, p.look_at, p.up
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        if self.calibrate:
            threading.Thread(target=self._calibrate, name="clod-view-timing", daemon=True).start()
        return server.get_port()

    def _prepare_rasteriser(self) -> None:
        # Build/load the C++ compositor in the caller's thread: a build interrupted inside a
        # daemon thread (the process exiting) would leave a stale lock in TORCH_EXTENSIONS_DIR.
        from clod_adapter.render.composite import cpp_extension_available

        cpp_extension_available()

    def stop(self) -> None:
        """Stop every client thread and the server."""
        for s in list(self._sessions.values()):
            s.close()
        if self.server is not None:
            self.server.stop()

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def _calibrate(self) -> None:
        try:
            self.timer = calibrate_raster_time(self.gaussians, self.timing_camera)
            self.timer_state = None if self.timer is not None else "n/a (nothing in view at the start camera)"
        except Exception as e:  # the estimate is optional; say why it is missing
            self.timer_state = f"n/a ({type(e).__name__}: {e})"
        for s in list(self._sessions.values()):
            s.dirty.set()

    def _on_connect(self, client) -> None:
        self._sessions[client.client_id] = _Session(self, client)

    def _on_disconnect(self, client) -> None:
        s = self._sessions.pop(client.client_id, None)
        if s is not None:
            s.close()

    # --- inspection (scripts, tests) --------------------------------------------------------
    def sessions(self) -> dict:
        """client id -> its session (``.mode``, ``.sv``, ``.budget``, ``.compare`` GUI handles,
        ``.record``)."""
        return dict(self._sessions)

    def wait_for_view(self, predicate: Callable[[ViewRecord], bool], timeout: float = 60.0,
                      client_id: Optional[int] = None) -> ViewRecord:
        """Block until some client's (or ``client_id``'s) latest :class:`ViewRecord` satisfies
        ``predicate``; returns it. Raises TimeoutError after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for cid, s in self._sessions.items():
                    if (client_id is None or cid == client_id) and s.record is not None and predicate(s.record):
                        return s.record
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no client view satisfied the condition within {timeout} s")
                self._cond.wait(min(left, 0.5))


def scene_camera_list(scene) -> list[tuple[str, object]]:
    """``(name, camera)`` of a scene's test views then its training views (names marked)."""
    out = [(f"test: {c.name}", c) for c in scene.test]
    out += [(f"train: {c.name}", c) for c in scene.train]
    return out
