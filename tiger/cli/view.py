"""``tiger view``: look at a scene in the browser, ask, select, edit and delete."""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import CliError, device_of, existing


def add_parser(sub) -> None:
    p = sub.add_parser(
        "view", help="open a scene in the browser: look, ask, select, edit, delete",
        description="Serve SCENE as a web page (viser) whose frames are drawn by TIGER's rasterizer at "
                    "the browser's camera: render modes (RGB, depth, alpha, language-feature PCA, "
                    "relevancy heat map), text queries and the point prompt (click an object) with "
                    "the selection highlighted and its box drawn, edits (recolor; ip2p+mvdream and "
                    "ip2p when their weights are found) and deletion in a worker with progress and "
                    "Cancel, Undo/Redo, and Save (PLY into --out). Binds to 127.0.0.1 unless --host "
                    "says otherwise. Ctrl-C stops it.",
        epilog="example: tiger view outputs/demo/scene.ply   (then open http://127.0.0.1:8080)\n"
               "         tiger view outputs/fox/scene_lang.ply --data ../shared/data/fox --port 8081",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="PLY (with or without lang_*), a `tiger prepare` folder, or a folder holding scene*.ply")
    p.add_argument("--data", default=None,
                   help="the capture (COLMAP / transforms.json) whose cameras to list "
                        "(default: cameras.json beside the PLY, when there)")
    p.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default: %(default)s)")
    p.add_argument("--port", type=int, default=8080, help="port (default: %(default)s)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default: %(default)s; another address lets anyone who can reach "
                        "it edit the scene)")
    p.add_argument("--models", default=None,
                   help="model folder or JSON config (CLIP for free text, ip2p/mvdream for edits; "
                        "default: $TIGER_MODELS)")
    p.add_argument("--text-embeddings", default=None,
                   help="torch.save'd {text: [512] tensor} instead of CLIP (default: text_embeddings.pt "
                        "beside the PLY, when there)")
    p.add_argument("--out", default=None, help="folder Save writes into (default: view/ beside the PLY)")
    p.set_defaults(func=run)


def _scene_file(path: str) -> Path:
    from .prepare import prepared_scene

    p = prepared_scene(existing(path, "scene"))  # a `tiger prepare` folder: its language scene
    if p.is_dir():
        found = sorted(p.glob("scene*.ply")) or sorted(p.glob("*.ply"))
        if not found:
            raise CliError(f"{p} holds no .ply scene")
        return found[0]
    if p.suffix.lower() != ".ply":
        raise CliError(f"{p} is not a .ply scene")
    return p


def _encoder(args: argparse.Namespace, ply: Path, device):
    """(encoder or None, why none)."""
    from tiger.retrieval.text import EmbeddingTable

    table = args.text_embeddings or (str(ply.with_name("text_embeddings.pt"))
                                     if ply.with_name("text_embeddings.pt").exists() else None)
    if table:
        return EmbeddingTable.load(existing(table, "--text-embeddings file")), ""
    try:
        from .text import text_encoder

        return text_encoder(args.models, None, device), ""
    except (ImportError, FileNotFoundError, ValueError, OSError) as e:
        return None, f"no text encoder ({str(e).splitlines()[0][:200]}): text queries are off; the point prompt works"


def _cameras(args: argparse.Namespace, ply: Path):
    if args.data:
        from .common import open_dataset

        return list(open_dataset(args.data, skip_missing=True).cameras)
    from tiger.scene.cameras_json import cameras_json_path, read_cameras_json

    path = cameras_json_path(ply)
    return read_cameras_json(path) if path.exists() else []


def run(args: argparse.Namespace) -> int:
    if not 0 < args.port < 65536:
        raise CliError(f"--port must be in 1..65535, got {args.port}")
    dev = device_of(args.device)
    ply = _scene_file(args.scene)
    try:
        import viser  # noqa: F401
    except ImportError:
        raise CliError("the viewer needs viser: pip install viser==1.1.1 (or the 'viewer' extra)") from None
    from tiger.scene import GaussianScene

    from tiger.viewer import serve
    from tiger.viewer.server import PortInUseError, check_port

    try:
        check_port(args.host, args.port)
    except PortInUseError as e:
        raise CliError(str(e)) from None
    scene = GaussianScene.load_ply(ply).to(dev)
    encoder, note = _encoder(args, ply, dev)
    if scene.lang is None:
        print(f"tiger view: {ply} has no language features (lang_*): look only; run `tiger embed` to ask, "
              "select, edit and delete")
    out = Path(args.out) if args.out else ply.parent / "view"
    print(f"tiger view: http://{args.host}:{args.port}  ({ply}, {len(scene)} Gaussians on {dev}; Save writes "
          f"into {out}; Ctrl-C stops)", flush=True)
    serve(scene, encoder=encoder, encoder_note=note, host=args.host, port=args.port, cameras=_cameras(args, ply),
          out_dir=out, models=args.models, device=dev)
    return 0
