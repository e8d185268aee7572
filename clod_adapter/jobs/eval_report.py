"""``clod-eval``'s report files: the tables (CSV, Markdown), the figures (quality against
frame time, frame time against the level, popping) and the JSON-safe record."""
from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Optional, Sequence


from ..io.atomic import atomic_save
from ..evaluate.frontier import Point, frontier


# --- outputs ----------------------------------------------------------------------------------
def csv_text(rows: list[dict], columns: Sequence[str]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]))
                    for k in columns})
    return buf.getvalue()
from .eval_methods import METHOD_REGISTRY, METHODS, finite


def jsonable(o):
    if isinstance(o, dict):
        return {k: jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [jsonable(v) for v in o]
    if isinstance(o, float):
        return finite(o)
    return o


def save_fig(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    atomic_save(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight"))
    plt.close(fig)


def plot_quality(rows: list[dict], x: str, xlabel: str, path: Path, extra=None, time_axis: bool = False,
                  mark: Optional[tuple] = None) -> None:
    """Quality against ``x``. ``time_axis``: markers only, each with a horizontal bar from the
    fastest to the slowest timing round, never joined by lines (a line across budgets would turn
    timing noise into a trend), and the x axis log-scaled. ``mark``: (x, label) of a dotted
    vertical line (the coarsest trained level, max_sv^-1.5)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = [m for m in ("psnr", "ssim", "lpips") if any(r[m] is not None for r in rows)]
    ncol = len(metrics) + (1 if extra else 0)
    fig, axes = plt.subplots(1, ncol, figsize=(4.2 * ncol, 3.4), squeeze=False)
    for ax, m in zip(axes[0], metrics):
        for method in METHODS:
            # ordered by Gaussian count, so the sweep's line follows the level of detail
            rs = sorted((r for r in rows if r["method"] == method and r[m] is not None and r[x] is not None),
                        key=lambda r: (r["gaussians"], r[x]))
            if not rs:
                continue
            c, ls, mk = METHOD_REGISTRY[method].style
            ms = 6 if method != "pretrained" else 11
            xs, ys = [r[x] for r in rs], [r[m] for r in rs]
            if time_axis:
                lo = [max(r[x] - (r.get("ms_min") if r.get("ms_min") is not None else r[x]), 0.0) for r in rs]
                hi = [max((r.get("ms_max") if r.get("ms_max") is not None else r[x]) - r[x], 0.0) for r in rs]
                ax.errorbar(xs, ys, xerr=[lo, hi], color=c, linestyle="none", marker=mk, ms=ms * 0.8,
                            capsize=2, elinewidth=0.8, label=method)
                # the method's frontier: its best quality within each time (lpips: lower is better)
                sign = -1.0 if m == "lpips" else 1.0
                fr = frontier(Point(method, "", xx, sign * yy) for xx, yy in zip(xs, ys))
                if len(fr) > 1:
                    ax.step([q.ms for q in fr], [sign * q.psnr for q in fr], where="post", color=c, lw=0.9,
                            alpha=0.7)
            else:
                ax.plot(xs, ys, color=c, linestyle=ls or "none", marker=mk, label=method, ms=ms)
        if mark is not None:
            ax.axvline(mark[0], color="0.4", linestyle=":", linewidth=1)
            ax.annotate(mark[1], (mark[0], 0.02), xycoords=("data", "axes fraction"), fontsize=7,
                        color="0.3", rotation=90, ha="right", va="bottom")
        ax.set_xlabel(xlabel, fontsize=8 if time_axis else None)
        if time_axis:
            from matplotlib.ticker import LogLocator, ScalarFormatter

            ax.set_xscale("log")
            ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            ax.xaxis.set_major_formatter(ScalarFormatter())
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_ylabel({"psnr": "PSNR (dB)", "ssim": "SSIM", "lpips": "LPIPS-alex (lower is better)"}[m])
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    if extra:
        extra(axes[0][-1])
    fig.tight_layout()
    save_fig(fig, path)


def plot_time_curve(rows: list[dict]):
    def draw(ax):
        rs = sorted((r for r in rows if r["method"] == "clod"), key=lambda r: r["s_v"])
        sv = [r["s_v"] for r in rs]
        for k, lab in (("ms_total", "total"), ("ms_select", "projection and LoD selection"), ("ms_raster", "rasterisation")):
            ax.plot(sv, [r[k] for r in rs], marker=".", label=lab)
        if rs and all(r.get("ms_min") is not None for r in rs):
            ax.fill_between(sv, [r["ms_min"] for r in rs], [r["ms_max"] for r in rs], color="C0", alpha=0.2,
                            label="total: fastest-slowest round")
        ax.set_ylim(bottom=0)
        ax.set_xlabel("s_v")
        ax.set_ylabel("median ms per frame")
        ax.set_title("render time, clod sweep", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return draw


def plot_popping(pop: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    ax.plot(pop["step_s_v"], pop["continuous_step"], marker=".", label="continuous (clod, s_v sweep)")
    ax.plot(pop["step_s_v"], pop["discrete_step"], drawstyle="steps-mid",
            label=f"discrete switch {pop['discrete_counts'][0]}->{pop['discrete_counts'][1]} G at s_v={pop['switch_s_v']:.2f}")
    ax.set_yscale("symlog", linthresh=1e-4)
    ax.set_xlabel("s_v")
    ax.set_ylabel("per-step image change (mean |dI|)")
    ax.set_title(f"popping: max step ratio discrete/continuous = {pop['ratio']:.1f}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_fig(fig, path)


def format_table(rows: list[dict]) -> str:
    """Short text table of the aggregated rows."""
    wm = max([len("method")] + [len(r["method"]) for r in rows]) + 1  # columns never run into each other
    ws = max([len("setting")] + [len(r["setting"]) for r in rows]) + 1
    head = f"{'method':<{wm}}{'setting':<{ws}}{'s_v':>6}{'Gaussians':>11}{'%':>6}{'PSNR':>7}{'SSIM':>7}{'LPIPS':>7}{'ms':>8}"
    lines = [head]
    for r in rows:
        f = lambda v, spec: ("-" if v is None else format(v, spec))  # noqa: E731
        lines.append(f"{r['method']:<{wm}}{r['setting']:<{ws}}{f(r['s_v'], '6.2f'):>6}{r['gaussians']:11.0f}"
                     f"{100 * r['fraction']:6.1f}{r['psnr']:7.2f}{r['ssim']:7.4f}{f(r['lpips'], '7.4f'):>7}"
                     f"{r['ms_total']:8.1f}")
    return "\n".join(lines)


def format_markdown(report: dict) -> str:
    """The report's headline tables as Markdown (``report.md``): quality per method at each
    budget, the adapted model's s_v sweep with render times, and the popping ratio."""
    rows = report["rows"]
    qt = report.get("quality_vs_time")
    head = [] if qt is None else ["## Quality against frame time", "", qt["verdict"], "", qt["cells_markdown"], "",
                                  "![PSNR against frame time](quality_vs_time.png)", "", "## Levels and budgets", ""]
    fmt = lambda v, f: "-" if v is None or (isinstance(v, float) and v != v) else format(v, f)  # noqa: E731
    budgets = [r["setting"] for r in rows if r["method"] == "clod_budget"]
    methods = [m for m in METHODS if m not in ("clod", "pretrained") and any(r["method"] == m for r in rows)]
    out = head + [f"{report['num_gaussians']['adapted']:,} Gaussians; views: {', '.join(report['views'])} "
           f"at {report['image_size'][0]}x{report['image_size'][1]}; {report['device']}, "
           f"{report['threads']} threads; constant-sigma c = {report['settings']['sigma_c']:g} "
           f"({report['settings']['sigma_c_rule']}).", "",
           "PSNR / SSIM / LPIPS (mean Gaussians rendered per view):", "",
           "| method | " + " | ".join(b.replace("budget=", "budget ") for b in budgets) + " |",
           "|---|" + "---|" * len(budgets)]
    for m in methods:
        cells = []
        for b in budgets:
            r = next((r for r in rows if r["method"] == m and r["setting"] == b), None)
            cells.append("-" if r is None else f"{fmt(r['psnr'], '.2f')} / {fmt(r['ssim'], '.3f')} / "
                         f"{fmt(r['lpips'], '.3f')} ({r['gaussians']:,.0f})")
        out.append(f"| {m} | " + " | ".join(cells) + " |")
    ref = next((r for r in rows if r["method"] == "pretrained"), None)
    if ref is not None:
        out += ["", f"Pretrained, full: {fmt(ref['psnr'], '.2f')} / {fmt(ref['ssim'], '.3f')} / "
                f"{fmt(ref['lpips'], '.3f')} ({ref['gaussians']:,.0f} Gaussians, {fmt(ref['ms_total'], '.0f')} ms, "
                f"rounds {fmt(ref.get('ms_min'), '.0f')}-{fmt(ref.get('ms_max'), '.0f')} ms)."]
    t = report.get("timing", {})
    out += ["", f"Adapted model over s_v (ms per frame = projection and LoD selection + rasterisation; median of "
            f"{t.get('repeats', 1) or 1} interleaved round(s) of the median over views; range: fastest-slowest round):", "",
            "| s_v | Gaussians | % | PSNR | SSIM | LPIPS | ms | ms range | ms select | ms raster | MB rendered |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if r["method"] == "clod":
            out.append(f"| {r['s_v']:.2f} | {r['gaussians']:,.0f} | {100 * r['fraction']:.1f} | "
                       f"{fmt(r['psnr'], '.2f')} | {fmt(r['ssim'], '.4f')} | {fmt(r['lpips'], '.4f')} | "
                       f"{fmt(r['ms_total'], '.1f')} | {fmt(r.get('ms_min'), '.1f')}-{fmt(r.get('ms_max'), '.1f')} | "
                       f"{fmt(r['ms_select'], '.1f')} | "
                       f"{fmt(r['ms_raster'], '.1f')} | {r['bytes'] / 1e6:.2f} |")
    st = report.get("storage")
    if st:
        out += ["", "Storage (MB): " + ", ".join(f"{k[:-6].replace('_', ' ')} {v / 1e6:.2f}" for k, v in st.items()
                                               if k.endswith("_bytes")) + "."]
        if st.get("dlod_levels"):
            out.append("dlod_finetuned: the full model plus one fine-tuned level per budget ("
                       + ", ".join(f"{k}: {v:,} Gaussians, cut by {st['dlod_ranking'][k]}" for k, v in st["dlod_levels"].items())
                       + f"; {st['dlod_iterations']} steps each).")
    pop = report["popping"]
    out += ["", f"Popping (camera {pop['camera']}, mean |dI| per step): continuous max "
            f"{pop['continuous_max']:.3g}, median {pop['continuous_median']:.3g}; discrete switch "
            f"{pop['discrete_max']:.3g}; ratio {pop['ratio']:.1f}."]
    return "\n".join(out) + "\n"
