"""Fine-tune a pretrained 3DGS model into a CLoD-GS model (the paper's robustness setting).

A per-Gaussian distance decay ``sigma_d`` is attached and trained with virtual distance scaling
(CLoD-GS, Cheng et al. ICLR 2026, Sec. 3). Two schedules (:data:`SCHEDULES`):

* ``"calibrated"`` (default): ``sigma_d`` starts from a static ranking (LightGaussian
  significance) mapped through Eq. 2 so that the top ``s_v^-1.5`` of the ranking is drawn at
  ``s_v`` (:func:`clod_adapter.lod.rule.calibrate_sigma_d`); each step draws ``s_v`` log-uniform in [1, max_sv],
  renders exactly ``s_v^-1.5`` of the Gaussians in view (the Eq. 2 mask at the solved ``s_v``,
  :mod:`clod_adapter.lod.budget`) with the window fade and the level gains of that share
  (:class:`clod_adapter.lod.rule.LodSettings`), and takes a step on the rendering loss. After the
  last step ``sigma_d`` is re-mapped from the order it has learned, so the drawn share at
  ``s_v`` is ``s_v^-1.5`` again (training pushes every decay up). The base attributes are frozen by default
  (``other_lr_scale = 0``): full detail is the input model.
* ``"paper"``: the paper's recipe: ``sigma_d`` initialised large, ``s_v ~ U(1, max_sv)``, Eq. 2
  fading, ``L = w_s (L_render + lambda_reg L_reg)`` with a straight-through ``eta``; the other
  attributes at ``other_lr_scale`` (0.1) of the official 3DGS learning rates.

No densification.

Public entry points: :class:`AdaptConfig`, :func:`prepare`, :func:`fit`, :func:`save_state`,
:func:`load_state`.
"""
from __future__ import annotations

import contextlib
import signal
from typing import Callable, Optional

import torch
from torch import Tensor

from ..lod import rule as lod
from ..lod.budget import Budget, critical_s_v
from ..lod_settings import EtaGradient
from ..gaussians import Gaussians
from .losses import clod_loss, render_loss
from ..lod.draw import render_lod
from ..lod.view import view_lod
from ..metrics import psnr
from .config import PARAM_NAMES, AdaptConfig
from .official import ADAM_EPS, means_lr, scene_extent
from .state import AdaptState, lr_groups


@torch.no_grad()
def max_normalized_distance(gaussians: Gaussians, cameras) -> Tensor:
    """[N] largest frustum-normalised distance d' of each Gaussian over ``cameras``."""
    dmax = torch.zeros(len(gaussians), dtype=torch.float32, device=gaussians.means.device)
    for cam in cameras:
        vm = cam.viewmat.to(gaussians.means)
        fr = lod.in_frustum(gaussians.means, vm, cam.K.to(gaussians.means), cam.width, cam.height)
        d = lod.normalized_distances(gaussians.means, lod.camera_center(vm), fr)
        dmax = torch.maximum(dmax, d.float())
    return dmax


@torch.no_grad()
def reference_distances(gaussians: Gaussians, cameras) -> Tensor:
    """[N] float32 reference d' of each Gaussian for :func:`lod.calibrate_sigma_d`: its mean
    frustum-normalised distance over the views whose frustum holds its centre (over all views
    when none does), so the drawn share at ``s_v`` is ``s_v^-1.5`` on average over the views.
    Streaming: O(N) memory whatever the number of views."""
    n = len(gaussians)
    dev = gaussians.means.device
    s_in = torch.zeros(n, dtype=torch.float64, device=dev)
    c_in = torch.zeros(n, dtype=torch.float64, device=dev)
    s_all = torch.zeros(n, dtype=torch.float64, device=dev)
    for cam in cameras:
        vm = cam.viewmat.to(gaussians.means)
        fr = lod.in_frustum(gaussians.means, vm, cam.K.to(gaussians.means), cam.width, cam.height)
        d = lod.normalized_distances(gaussians.means, lod.camera_center(vm), fr).double()
        s_all += d
        s_in += torch.where(fr, d, torch.zeros_like(d))
        c_in += fr.double()
    return torch.where(c_in > 0, s_in / c_in.clamp_min(1), s_all / max(len(cameras), 1)).float()


@torch.no_grad()
def view_statistics(gaussians: Gaussians, cameras) -> dict:
    """What calibration needs from the training views (O(N) memory).

    Returns:
        dict of [N] float32 tensors: ``d_ref`` (:func:`reference_distances`) and ``cost`` (mean
        frame cost over the views: :func:`clod_adapter.lod.cost.splat_cost` at the base level,
        clipped ellipse pixels, 0 in views that do not draw it).
    """
    from ..lod.cost import splat_cost

    g = gaussians.detach().with_sigma_d(None)
    n = len(g)
    dev = g.means.device
    d_ref = reference_distances(g, cameras)
    cost = torch.zeros(n, dtype=torch.float64, device=dev)
    for cam in cameras:
        v = view_lod(g, cam)
        ids = torch.nonzero(v.visible, as_tuple=False).squeeze(1)
        cost.index_add_(0, ids, splat_cost(v, ids).double())
    return {"d_ref": d_ref, "cost": (cost / max(len(cameras), 1)).float()}


@torch.no_grad()
def ranking_scores(gaussians: Gaussians, cameras, ranking: str = "lightgaussian") -> Tensor:
    """[N] the static ranking the calibrated schedule starts from (higher = kept longer):
    LightGaussian global significance over ``cameras`` or the opacity."""
    if ranking == "opacity":
        return gaussians.opacities.detach().float()
    from ..lod.rankings import lightgaussian_significance

    return lightgaussian_significance(gaussians.detach(), cameras)


def calibrated_sigma_d(score: Tensor, opacities: Tensor, stats: dict, cfg: AdaptConfig) -> Tensor:
    """[N] ``sigma_d`` of the calibrated schedule: :func:`lod.calibrate_sigma_d` of ``score`` at
    the reference distances, on quantiles of ``cost^cfg.cost_exponent`` (``stats`` from
    :func:`view_statistics`; count quantiles for exponent 0)."""
    beta = cfg.cost_exponent
    return lod.calibrate_sigma_d(score, opacities, stats["d_ref"], tau=cfg.tau, eps=cfg.eps,
                                 fade_width=cfg.fade_width,
                                 cost=stats["cost"].double().clamp_min(1e-12) ** beta if beta > 0 else None)


def merged_order(learned: Tensor, start: Tensor, share: float) -> Tensor:
    """[N] float64 ranking score (higher = kept longer) that keeps the ``learned`` order for its
    top ``share`` of the Gaussians (by count; ``round(share N)`` of them) and ranks every other
    one by ``start`` below them. Ties are broken by index, as in :func:`lod.calibrate_sigma_d`.

    Args:
        learned: [N] learned ranking score (e.g. the reference critical ``s_v``).
        start: [N] starting ranking score (e.g. LightGaussian significance).
        share: in [0, 1]; 1 returns the learned order, 0 the starting one.
    """
    n = learned.numel()

    def ranks(score):  # 0 = kept longest
        r = torch.empty(n, dtype=torch.float64, device=score.device)
        r[torch.sort(-score.detach().double(), stable=True).indices] = torch.arange(
            n, dtype=torch.float64, device=score.device)
        return r
    r_learned = ranks(learned)
    keep = r_learned < round(share * n)
    # kept: scores in (n, 2n]; the others: (0, n], by the starting order
    return torch.where(keep, 2.0 * n - r_learned, n - ranks(start))


@torch.no_grad()
def recalibrate(state: "AdaptState", cameras, cfg: AdaptConfig) -> None:
    """Re-map ``sigma_d`` from the order it has learned (the reference critical s_v at each
    Gaussian's reference distance), in place: the learned order at the reference distance is
    kept and the drawn share at ``s_v`` is again ``s_v^-1.5`` (:func:`calibrated_sigma_d`)."""
    g = state.gaussians().detach()
    stats = view_statistics(g, cameras)
    s_ref = critical_s_v(g.opacities, stats["d_ref"], g.sigma_d, cfg.tau, cfg.eps)
    if cfg.trained_order_share < 1.0:
        s_ref = merged_order(s_ref, ranking_scores(g, cameras, cfg.ranking), cfg.trained_order_share)
    new = calibrated_sigma_d(s_ref, g.opacities, stats, cfg)
    state.params["sigma_d"].data.copy_(new.to(state.params["sigma_d"]))


#: candidate init attenuations, most aggressive first (:func:`calibrate_init`).
INIT_CANDIDATES = (0.8, 0.9, 0.95, 0.98, 0.99, 0.995, 0.999)


@torch.no_grad()
def calibrate_init(gaussians: Gaussians, d_norm_max: Tensor, cameras, images, cfg: AdaptConfig,
                   max_drop_db: float = 0.02, views: int = 3, backend: str = "auto") -> tuple[float, float]:
    """Pick the smallest attenuation of :data:`INIT_CANDIDATES` whose s_v = 1 render loses at
    most ``max_drop_db`` PSNR against the input on up to ``views`` training views.

    A smaller attenuation starts ``sigma_d`` closer to where it cuts Gaussians at large s_v, so
    fewer steps are spent just getting there; the check keeps step 0 rendering like the input.

    Returns:
        (attenuation, measured PSNR drop in dB).
    """
    idx = torch.linspace(0, len(cameras) - 1, min(views, len(cameras))).round().long().tolist()
    base = [psnr(render_lod(gaussians, cameras[i], None, background=cfg.background,
                            backend=backend).image, images[i]) for i in idx]
    drop = 0.0
    for a in INIT_CANDIDATES:
        g = gaussians.with_sigma_d(lod.init_sigma_d(d_norm_max, a).to(gaussians.means))
        p = [psnr(render_lod(g, cameras[i], 1.0, tau=cfg.tau, eps=cfg.eps, background=cfg.background,
                             backend=backend).image, images[i]) for i in idx]
        drop = max(b - q for b, q in zip(base, p))
        if drop <= max_drop_db:
            return a, drop
    return INIT_CANDIDATES[-1], drop


def prepare(gaussians: Gaussians, train_cameras, cfg: AdaptConfig, train_images=None,
            backend: str = "auto") -> AdaptState:
    """Attach ``sigma_d`` (and zero level gains) and build the optimiser state for :func:`fit`.

    Calibrated schedule: ``sigma_d`` from :func:`ranking_scores` through
    :func:`lod.calibrate_sigma_d` at :func:`reference_distances`. Paper schedule:
    :func:`clod_adapter.lod.rule.init_sigma_d` over the training views; with
    ``cfg.init_attenuation`` None the attenuation is calibrated on ``train_images``
    (:func:`calibrate_init`; 0.995 when no images are given). A model that already has
    ``sigma_d`` (and gains) keeps them. What was done is stored in ``state.init``."""
    g = gaussians.clone()
    init = {}
    if g.sigma_d is None and cfg.schedule == "calibrated":
        scores = ranking_scores(g, train_cameras, cfg.ranking)
        stats = view_statistics(g, train_cameras)
        g = g.with_sigma_d(calibrated_sigma_d(scores, g.opacities, stats, cfg).to(g.means))
        init = {"ranking": cfg.ranking, "cost_exponent": cfg.cost_exponent}
    elif g.sigma_d is None:
        dmax = max_normalized_distance(g, train_cameras)
        att = cfg.init_attenuation
        if att is None and train_images is not None:
            att, drop = calibrate_init(g, dmax, train_cameras, train_images, cfg, backend=backend)
            init = {"attenuation": att, "train_psnr_drop_db": drop}
        elif att is None:
            att = 0.995
        init.setdefault("attenuation", att)
        g = g.with_sigma_d(lod.init_sigma_d(dmax, att).to(g.means))
    train_others = cfg.other_lr_scale > 0
    params = {}
    for name in PARAM_NAMES:
        t = getattr(g, name).detach().clone().contiguous()
        params[name] = torch.nn.Parameter(t, requires_grad=(name == "sigma_d") or train_others)
    for name in cfg.gain_names:
        have = getattr(g, name)
        shape = (len(g), 1, 3) if name == "sh0_gain" else (len(g),)
        t = have.detach().clone() if have is not None else torch.zeros(shape, dtype=g.means.dtype, device=g.means.device)
        params[name] = torch.nn.Parameter(t.contiguous())
    extent = scene_extent(train_cameras)
    opt = torch.optim.Adam(lr_groups(params, cfg, extent), eps=ADAM_EPS)
    gen = torch.Generator().manual_seed(cfg.seed)
    return AdaptState(params=params, optimizer=opt, generator=gen, extent=extent, init=init,
                      lod=cfg.lod_settings(), extra=dict(g.extra))


class StopFlag:
    """Turns SIGINT/SIGTERM into a flag checked at safe points (between iterations; the
    pipeline also checks it between phases), so the state is saved, never half-written.

    The handler only sets ``stop`` while ``abortable`` is False (a second signal during a
    state save changes nothing). While ``abortable`` is True (phases that write nothing), it
    also raises KeyboardInterrupt at once. Outside the main thread no handler is installed.
    """

    def __init__(self, abortable: bool = False) -> None:
        self.stop = False
        self.signum: Optional[int] = None
        self.state_saved = False  # set by callers once a resumable state is on disk
        self._abortable = abortable
        self._old = {}

    def __enter__(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._old[sig] = signal.signal(sig, self._handle)
            except ValueError:  # not in the main thread
                pass
        return self

    def reinstall(self) -> None:
        """Put our handlers back after a library replaced them (pycolmap's glog installs a
        failure-signal handler for SIGTERM when it is first imported, which the lazy COLMAP
        import does in the middle of a run)."""
        for sig in list(self._old):
            signal.signal(sig, self._handle)

    def _handle(self, signum, frame) -> None:
        self.stop = True
        self.signum = signum
        if self._abortable:
            raise KeyboardInterrupt

    @property
    def abortable(self) -> bool:
        return self._abortable

    def set_abortable(self, value: bool) -> None:
        """Enter/leave an abortable phase; entering one after a signal raises KeyboardInterrupt."""
        self._abortable = bool(value)
        if self._abortable and self.stop:
            raise KeyboardInterrupt

    def __exit__(self, *exc) -> None:
        for sig, h in self._old.items():
            signal.signal(sig, h)
        self._old = {}


@torch.no_grad()
def weighted_count(view, share: float, cost_exponent: float) -> int:
    """How many Gaussians a level of ``share`` of the view's weighted cost draws: the longest
    prefix of the Gaussians in view by critical ``s_v`` (descending, ties by index: the order
    every budget uses) whose ``sum cost^cost_exponent`` is at most ``share`` of the total
    (``cost`` = :func:`clod_adapter.lod.cost.base_costs`, clipped ellipse pixels at the base level;
    the prefix by :func:`clod_adapter.lod.cost.ordered_prefix_count`, without a full sort)."""
    from ..lod.cost import base_costs, ordered_prefix_count

    pool = torch.nonzero(view.visible, as_tuple=False).squeeze(1)
    if pool.numel() == 0 or share >= 1.0:  # all of it (a sum in another order may round past the total)
        return int(pool.numel())
    w = base_costs(view, pool).clamp_min(1e-12) ** float(cost_exponent)
    return ordered_prefix_count(view.critical.index_select(0, pool), w, float(share) * float(w.sum()))


def view_loss(g: Gaussians, camera, gt: Tensor, s_v: float, cfg: AdaptConfig, backend: str = "auto"):
    """One training view's render and loss at ``s_v`` (the body of a step of :func:`fit`).

    Returns:
        (:class:`clod_adapter.lod.draw.LodRender`, scalar loss tensor).
    """
    if cfg.schedule == "calibrated" and cfg.cost_exponent > 0:
        # the level's exact share of the view's weighted cost, drawn with the level's gains
        view = view_lod(g, camera, tau=cfg.tau, eps=cfg.eps)
        k = weighted_count(view, lod.target_fraction(s_v), cfg.cost_exponent)
        out = render_lod(g, camera, budget=Budget(count=max(k, 1), min_s_v=0.0), tau=cfg.tau, eps=cfg.eps,
                         background=cfg.background, backend=backend, view=view)
    elif cfg.schedule == "calibrated":
        # the level's exact share of the Gaussians in view, drawn with the level's gains
        out = render_lod(g, camera, budget=Budget(in_view=lod.target_fraction(s_v), min_s_v=0.0),
                         tau=cfg.tau, eps=cfg.eps, background=cfg.background,
                         backend=backend)
    else:
        out = render_lod(g, camera, s_v, tau=cfg.tau, eps=cfg.eps,
                         eta_grad=EtaGradient(cfg.eta_estimator, cfg.temperature),
                         background=cfg.background, backend=backend)
    l_render = render_loss(out.image, gt)
    loss, _ = clod_loss(l_render, out.eta, s_v, cfg.max_sv, cfg.lambda_reg)
    if cfg.level_weighting == "uniform":
        # divided out rather than not applied: the same float rounding as every model adapted so
        # far (--deterministic runs reproduce to the last digit)
        loss = loss / lod.scale_weight(s_v, cfg.max_sv)
    return out, loss


def _draw_views(state: AdaptState, n_views: int, cfg: AdaptConfig) -> list:
    """One step's (view index, s_v) pairs: views shuffled without replacement per epoch, each
    with its own ``s_v``, drawn in that order from the state's generator (view, s_v, ...)."""
    picks = []
    for _ in range(cfg.views_per_step):
        if not state.order:
            state.order = torch.randperm(n_views, generator=state.generator).tolist()
        vi = state.order.pop()
        picks.append((vi, lod.sample_s_v(cfg.max_sv, state.generator, cfg.s_v_sampling)))
    return picks


def _record(h: dict, picks: list, rows: dict, ema: dict) -> None:
    """Append one step's records to the history ``h`` and update the progress averages ``ema``."""
    for j, (vi, s_v) in enumerate(picks):
        loss_j, p, eta = rows[j]
        h["s_v"].append(round(s_v, 4))
        h["eta"].append(round(eta, 5))
        h["loss"].append(round(loss_j, 6))
        h["psnr"].append(round(p, 3))
        for k, v in (("loss", h["loss"][-1]), ("psnr", p)):
            ema[k] = v if ema[k] is None else 0.9 * ema[k] + 0.1 * v


def _backward_views(g: Gaussians, picks: list, cameras, images, cfg: AdaptConfig, backend: str, rank: int,
                    world: int) -> dict:
    """One step's views of this rank (``j mod world == rank`` of ``picks``, ``(view, s_v)`` pairs):
    each rendered at its ``s_v``, its loss backpropagated (gradients accumulate in ``g``'s leaves).
    Returns ``{j: (loss, PSNR dB, eta)}``."""
    rows = {}
    for j, (vi, s_v) in enumerate(picks):
        if j % world != rank:
            continue
        # grad on even when the caller is inside torch.no_grad() (an evaluation loop):
        # without it the step would silently train nothing
        with torch.enable_grad():
            out, loss = view_loss(g, cameras[vi], images[vi], s_v, cfg, backend)
            if loss.requires_grad:
                loss.backward()
        rows[j] = (float(loss.detach()), psnr(out.image, images[vi]), float(out.eta.detach()))
        del out, loss
    return rows


def _after_step(state: AdaptState, cameras, cfg: AdaptConfig, picks: list, rows: dict, ema: dict, bar) -> None:
    """After a step's Adam update: the calibrated schedule's :func:`recalibrate` when due, the
    step's records (:func:`_record`) and the progress bar."""
    if cfg.schedule == "calibrated" and (
            state.iteration == cfg.iterations
            or (cfg.recalibrate_every and state.iteration % cfg.recalibrate_every == 0)):
        recalibrate(state, cameras, cfg)
    _record(state.history, picks, rows, ema)
    # frac: the rendered fraction eta of the step (not tqdm's "time remaining")
    bar.set_postfix(loss=f"{ema['loss']:.4f}", psnr=f"{ema['psnr']:.2f}",
                    s_v=f"{picks[-1][1]:.2f}", frac=f"{rows[len(picks) - 1][2]:.3f}", refresh=False)
    bar.update(1)


def fit(
    state: AdaptState,
    train_cameras,
    train_images,
    cfg: AdaptConfig,
    *,
    backend: str = "auto",
    progress: bool = True,
    on_interrupt: Optional[Callable[[AdaptState], None]] = None,
    max_steps: Optional[int] = None,
    stop: Optional[StopFlag] = None,
    on_step: Optional[Callable[[AdaptState], None]] = None,
    group=None,
) -> bool:
    """Run (or continue) the fine-tuning from ``state.iteration`` to ``cfg.iterations``.

    Each step: ``cfg.views_per_step`` training views (shuffled, without replacement per
    epoch), each with its own ``s_v`` (:attr:`AdaptConfig.s_v_sampling`) (drawn in that order from the state's
    generator: view, s_v, view, s_v, ...), rendered at ``s_v``; ``L = w (L_render + lambda_reg
    L_reg)`` (``w``: the level weighting); one Adam step on the mean of the views' gradients;
    calibrated schedule: :func:`recalibrate` every ``cfg.recalibrate_every`` steps and after
    the last.

    Args:
        state: from :func:`prepare` or :func:`load_state`; updated in place.
        train_cameras, train_images: training views and their [H, W, 3] float images in [0, 1]
            (any sequence; only the views rendered here are indexed).
        cfg: the run's settings.
        backend: rasteriser backend.
        progress: show progress with loss, PSNR, s_v and rendered fraction (``frac``): a tqdm
            bar when stderr is a terminal, else a plain line every 10 %.
        on_interrupt: called with the state when SIGINT/SIGTERM stops the run early.
        max_steps: run at most this many steps in this call (the schedule still spans
            ``cfg.iterations``); None: run to the end.
        stop: an entered :class:`StopFlag` to use (the caller's signal handling, put in its
            non-abortable mode for the loop); None: install one for the duration of the call.
        on_step: called with the state after each completed step.
        group: a :class:`clod_adapter.train.distributed.Group` for data-parallel training (each rank
            renders views ``j`` with ``j mod world_size == rank`` of every step, gradients and
            the step's records are summed over the ranks, and a signal on any rank stops all of
            them after the same step); None: one process.

    Returns:
        True when all iterations ran, False when interrupted or stopped by ``max_steps``
        (state holds the progress).

    Raises:
        clod_adapter.train.distributed.PeerLost: (``group`` given) another rank stopped answering.
    """
    from ..progress import progress_bar

    # a tqdm bar on a terminal; a plain line every 10 % in a log (stderr not a terminal)
    bar = progress_bar(cfg.iterations, "clod-adapt", unit="it", initial=state.iteration, disable=not progress)
    ema = {"loss": None, "psnr": None}
    stop_at = cfg.iterations if max_steps is None else min(cfg.iterations, state.iteration + max_steps)
    if stop is None:
        ctx = StopFlag()
    else:
        stop.set_abortable(False)
        ctx = contextlib.nullcontext(stop)
    views = cfg.views_per_step
    rank, world = (group.rank, group.world_size) if group is not None else (0, 1)
    agreed_stop = False  # data-parallel: a signal on any rank, agreed in the step's reduction

    with ctx as flag:
        stopping = (lambda: agreed_stop) if group is not None else (lambda: flag.stop)
        while state.iteration < stop_at:
            if stopping():
                bar.close()
                if on_interrupt is not None:
                    on_interrupt(state)
                return False
            it = state.iteration
            picks = _draw_views(state, len(train_cameras), cfg)
            for grp in state.optimizer.param_groups:
                if grp["name"] == "means":
                    grp["lr"] = means_lr(it, cfg.iterations, state.extent, scale=cfg.other_lr_scale)
            with torch.enable_grad():
                g = state.gaussians()
            state.optimizer.zero_grad(set_to_none=True)
            rows = _backward_views(g, picks, train_cameras, train_images, cfg, backend, rank, world)
            if group is not None or views > 1:
                from .distributed import combine_step

                rows, agreed_stop = combine_step(state.optimizer, rows, views, group, stop=flag.stop)
            state.optimizer.step()
            state.iteration += 1
            _after_step(state, train_cameras, cfg, picks, rows, ema, bar)
            if on_step is not None:
                on_step(state)
        if stopping() and state.iteration >= stop_at:
            # a signal during the last step: the loop is done, report it all the same
            bar.close()
            if on_interrupt is not None:
                on_interrupt(state)
            return False
    bar.close()
    return state.iteration >= cfg.iterations
