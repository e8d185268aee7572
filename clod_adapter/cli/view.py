"""``clod-view``: look at a level-of-detail model in the browser (viser).

    clod-view ADAPTED.ply [--images SCENE] [--resolution R] [--port P] [--host 127.0.0.1]
              [--background black|white] [--max-sv X] [--max-drawn N] [--no-timing]

Serves a local web viewer (viser; its client is bundled, nothing is fetched at run time) until
Ctrl-C / SIGTERM (exit 0). Exit status 2 on bad input: one line on stderr, nothing served.
Needs the viewer extra: ``pip install -e ".[viewer]"``.
"""
from __future__ import annotations

import argparse
import signal
import socket
import sys
import threading
from pathlib import Path

from clod_adapter.cli import common
from clod_adapter.cli.common import EXIT_BAD_INPUT


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="clod-view",
        description="Interactive level-of-detail viewer: drag s_v (or a budget) and fly around; the "
                    "selection is recomputed for each browser camera with our LoD rule.",
    )
    p.add_argument("ply", help="model: the .ply from clod-adapt (with sigma_d), or a plain 3DGS .ply / "
                               "compressed .ply / gsplat ckpt_*.pt (shown without LoD)")
    common.add_scene_flags(p)  # the scene's first test camera starts the view; its views are offered
    p.add_argument("--port", type=int, default=8080,
                   help="port (default 8080; the next free one if taken; 0 = any free port)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only)")
    p.add_argument("--background", default="black", choices=("black", "white"))
    p.add_argument("--max-sv", type=float, default=None,
                   help="trained maximum s_v; the slider runs to twice it (default: from "
                        "adapt_state.safetensors beside the .ply, else 5)")
    p.add_argument("--max-drawn", type=int, default=None,
                   help="send at most this many Gaussians per update (default 2,000,000; 32 bytes each)")
    p.add_argument("--no-timing", action="store_true",
                   help="skip timing our CPU rasteriser at startup (no ms estimate in the panel)")
    return p


def _one_line(e: object) -> str:
    return " ".join(str(e).split("\n")).strip()


def _fail(msg: str) -> int:
    print(f"clod-view: error: {_one_line(msg)}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _check_bind(host: str, port: int) -> str | None:
    """None if ``host`` can be listened on (the port may be taken: viser moves on), else why not."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as e:
        return f"--host {host}: not a usable address ({e})"
    fam, _, _, _, addr = infos[0]
    s = socket.socket(fam, socket.SOCK_STREAM)
    try:
        s.bind((addr[0], 0))
    except OSError as e:
        return f"--host {host}: cannot listen on it ({e.strerror or e})"
    finally:
        s.close()
    return None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not 0 <= args.port <= 65535:
        return _fail(f"--port {args.port}: must be in 0..65535")
    if args.max_drawn is not None and args.max_drawn < 1:
        return _fail(f"--max-drawn {args.max_drawn}: must be >= 1")
    if args.max_sv is not None and not (1.0 <= args.max_sv < float("inf")):
        return _fail(f"--max-sv {args.max_sv}: must be a finite number >= 1")
    try:
        from clod_adapter.viewer.app import LodViewer, require_viser, scene_camera_list

        require_viser()
    except ImportError as e:
        return _fail(str(e))
    from clod_adapter.io.ply import PlyFormatError
    from clod_adapter.io.scene import SceneError
    from clod_adapter.io.load import load_scene
    from clod_adapter.viewer.model import load_view_model, model_max_sv
    from clod_adapter.viewer.selection import DEFAULT_MAX_DRAWN

    ply = Path(args.ply)
    try:
        model = load_view_model(ply)
        cams = []
        if args.images:
            scene = load_scene(args.images, resolution=args.resolution)
            cams = scene_camera_list(scene)
            if not cams:
                return _fail(f"{args.images}: the scene has no cameras")
    except (PlyFormatError, SceneError, FileNotFoundError) as e:
        return _fail(str(e))
    except OSError as e:
        return _fail(f"{e.filename or ply}: {e.strerror or e}")
    why = _check_bind(args.host, args.port)
    if why:
        return _fail(why)

    max_sv = args.max_sv if args.max_sv is not None else model_max_sv(ply, model)
    bg = (1.0, 1.0, 1.0) if args.background == "white" else (0.0, 0.0, 0.0)
    if not args.no_timing:
        print("clod-view: loading our CPU rasteriser for the ms estimate (a one-time C++ build "
              "takes 1-3 min) ...", flush=True)
    viewer = LodViewer(model, max_sv=max_sv, scene_cameras=cams, background=bg,
                       max_drawn=args.max_drawn or DEFAULT_MAX_DRAWN, calibrate=not args.no_timing,
                       title=f"clod-view: {ply.name}")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    port = viewer.start(host=args.host, port=args.port)
    lod = "sigma_d: LoD slider 1.." + f"{viewer.sv_max:g}" if model.sigma_d is not None else "no sigma_d: no LoD"
    print(f"clod-view: {ply} ({len(model):,} Gaussians, {lod}) at http://{args.host}:{port}  "
          f"(Ctrl-C to stop)", flush=True)
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    print("clod-view: stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
