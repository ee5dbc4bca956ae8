"""``tiger edit``: change the object a text names, following an instruction (paper §3.2)."""
from __future__ import annotations

import argparse
import json
import logging

import torch

from tiger.utils.dtypes import DTYPE_NAMES
from tiger.utils.video import KINDS as VIDEO_KINDS

from .common import (CliError, Summary, add_common, add_selection_options, add_skip_missing,
                     check_selection_or_refuse, claim_output, command_elapsed_s, device_of, finish_output,
                     load_scene, open_dataset, output_dir, run_settings)
from .text import text_encoder

GUIDANCES = ("ip2p+mvdream", "ip2p", "mvdream", "recolor")
log = logging.getLogger(__name__)
#: CPU time of a recolour edit: about CPU_WARN_MINUTES per CPU_WARN_PIXEL_STEPS (steps x size^2),
#: measured on 2 cores (the defaults, 1200 steps at 512 px, took ~13 min).
CPU_WARN_PIXEL_STEPS, CPU_WARN_MINUTES = 1200 * 512 ** 2 // 13, 1.0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "edit", help="edit the object a text names with an instruction (CSD, or a plain recolour)",
        description="Retrieve the Gaussians the --target text names, place 4 cameras around them every "
                    "step, and optimise only those Gaussians (updates scaled by relevance, colour "
                    "view-independent, top-1 % densification) so that the renders follow the guidance: "
                    "Coherent Score Distillation of InstructPix2Pix and MVDream (needs their weights, "
                    "--models), or 'recolor' (no weights: the object's pixels pulled toward a colour "
                    "named in the instruction, shading kept). Writes edited.ply (with lang_*), "
                    "before_after.png (4 views), a turntable video and edit.json (settings, time, "
                    "metrics). Ctrl-C leaves a checkpoint that --resume continues exactly.",
        epilog='example: tiger edit outputs/demo/scene.ply --target ball "make it red" --guidance recolor '
               "--text-embeddings outputs/demo/text_embeddings.pt --out outputs/demo/edit_red",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="PLY with lang_* features and their PCA basis, or a `tiger prepare` folder")
    p.add_argument("instruction", help='the edit instruction, e.g. "make it look like a watermelon"')
    p.add_argument("--target", required=True, help="text naming the object to edit")
    add_common(p, models=True)
    p.add_argument("--guidance", choices=GUIDANCES, default="ip2p+mvdream",
                   help="gradient source (default: %(default)s; 'recolor' needs no weights)")
    p.add_argument("--color", default=None,
                   help="recolor: colour name, #rrggbb or r,g,b (default: the colour named in the instruction)")
    p.add_argument("--steps", type=int, default=1200, help="optimisation steps (default: %(default)s)")
    p.add_argument("--view-pool", type=int, default=256,
                   help="draw each step's 4 cameras from this many sets sampled at the start, their original "
                        "renders made once (as good as fresh cameras on the analytic edit's known answer, "
                        "and faster); 0: fresh cameras every step, as the paper (default: %(default)s)")
    p.add_argument("--size", type=int, default=512, help="edit render size in pixels (square; default: %(default)s)")
    p.add_argument("--dtype", choices=("auto", *DTYPE_NAMES), default="auto",
                   help="diffusion models' dtype (auto: bf16 on a GPU that has it, else fp16; fp32 on the CPU)")
    p.add_argument("--cuda-graph", action=argparse.BooleanOptionalAction, default=None,
                   help="replay each guidance step as a CUDA graph (default: on with a CUDA --device)")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.pt when it exists; refused, naming what differs, when "
                        "OUT holds an edit of another scene, target, instruction or settings")
    p.add_argument("--data", default=None,
                   help="the scene's dataset: its cameras decide 360° vs forward-facing views (default: 360°)")
    add_skip_missing(p)
    p.add_argument("--text-embeddings", default=None,
                   help="torch.save'd {text: [512] tensor} instead of CLIP weights")
    add_selection_options(p, guarded=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--video", choices=VIDEO_KINDS, default="auto",
                   help="turntable video (auto: H.264 MP4, else VP8/VP9 WebM, else GIF: all play in "
                        "browsers; default: %(default)s); mp4 or webm without an encoder here is "
                        "refused before the edit starts")
    p.set_defaults(func=run)


def _cameras(data, skip_missing: bool = False):
    if not data:
        return None
    return open_dataset(data, skip_missing).cameras


def run(args: argparse.Namespace) -> int:
    from tiger.edit import EditConfig, edit, resolve_target
    from tiger.edit.build import build_guidance
    from tiger.edit.pictures import before_after_grid
    from tiger.scene import render_rgb
    from tiger.edit.target import EmptyTargetError
    from tiger.eval.edit import locality, locality_text
    from tiger.utils.images import save_png
    from tiger.utils.threads import in_background
    from tiger.utils.video import check_video_kind, write_video

    if args.steps < 1 or args.size < 16:
        raise CliError("--steps must be >= 1 and --size >= 16")
    if args.view_pool < 0:
        raise CliError("--view-pool must be >= 0 (0: fresh cameras every step)")
    try:  # an explicit --video this machine cannot write is refused now, not after the edit
        check_video_kind(args.video)
    except RuntimeError as e:
        raise CliError(f"--video {args.video}: {e}") from None
    dev = device_of(args.device)
    if args.cuda_graph and dev.type != "cuda":
        raise CliError(f"--cuda-graph needs a CUDA --device, got {dev}")
    settings = run_settings(args, ignore=("cuda_graph", "dtype", "video"))
    output_dir(args.out, args.force or args.resume, create=False)  # refusals below leave no folder
    needed = [m for m in ("ip2p", "mvdream") if m in args.guidance.split("+")]
    if needed:
        from tiger.models.paths import require_models

        require_models(needed, config=args.models,
                       hint="Without these weights, `--guidance recolor` edits the object's colour (no models).")
    if args.guidance == "recolor" and dev.type == "cpu" and args.steps * args.size ** 2 > CPU_WARN_PIXEL_STEPS:
        log.warning("edit on the CPU: %d steps of 4 views at %d px take about %.0f min here (try --steps 200 "
                    "--size 256, or a GPU)", args.steps, args.size,
                    args.steps * args.size ** 2 / CPU_WARN_PIXEL_STEPS * CPU_WARN_MINUTES)
    elif needed and dev.type == "cpu":
        log.warning("edit on the CPU runs the diffusion models (%s) every step: expect hours; use a GPU "
                    "(--device cuda)", "+".join(needed))
    dtype = None if args.dtype == "auto" else DTYPE_NAMES[args.dtype]

    def build():  # MVDream loads now too, unless a resumed edit may not need it (it loads on first use)
        return build_guidance(args.guidance, args.instruction, models=args.models, device=dev,
                              color=args.color, seed=args.seed, dtype=dtype, cuda_graph=args.cuda_graph,
                              mvdream_kwargs=None if args.resume else {"lazy": False})

    # The diffusion models are read and built while the scene, CLIP and the retrieval load (both
    # mostly file reads and host work).
    guidance_ready = in_background(build, "tiger-edit-models") if needed else build
    scene = load_scene(args.scene, dev)
    if scene.lang is None:
        raise CliError(f"{args.scene} has no language features (lang_*); run `tiger embed` first")
    encoder = text_encoder(args.models, args.text_embeddings, dev, scene, args.scene)
    tau = args.tau
    try:
        target = resolve_target(scene, args.target, encoder=encoder, tau=tau, score=args.score)
    except EmptyTargetError as e:
        raise CliError(f"--target {args.target!r} retrieves no Gaussian (tau={args.tau}); try another text "
                       "or a lower --tau") from e
    check_selection_or_refuse(scene, target.mask, args.target, args.force, "edit")
    guidance = guidance_ready()
    cams = _cameras(args.data, args.skip_missing)
    out = claim_output(args.out, "edit", settings, force=args.force, resume=args.resume)
    cfg = EditConfig(steps=args.steps, width=args.size, height=args.size, seed=args.seed, view_pool=args.view_pool)
    res = edit(scene, target, guidance, cameras=cams, config=cfg, checkpoint=out / "checkpoint.pt", resume=args.resume)
    res.scene.save_ply(out / "edited.ply")
    from tiger.edit.views import ObjectViews

    views = ObjectViews(target.center, target.bbox_min, target.bbox_max, capture=cams,
                        force_360=True if not cams else None, width=args.size, height=args.size)
    bg = torch.tensor(cfg.background)
    frames = list(render_rgb(res.scene, views.fixed(36), bg).cpu())
    # The turntable is the longest output to write (profiled on the H100, the command still waited
    # ~3 s for it after the metrics): encoded (OpenCV/Pillow release the GIL) while the rest is made.
    video_ready = in_background(lambda: write_video(frames, out / "turntable", kind=args.video), "tiger-edit-video")
    save_png(out / "before_after.png", before_after_grid(scene, res.scene, views.fixed(4), bg))
    metrics = {"locality": locality(scene, res.scene, views.fixed(8), target.mask, res.editable)}
    if encoder is not None and hasattr(encoder, "clip"):
        from tiger.eval.edit import clip_metrics

        path = views.fixed(8)
        before = render_rgb(scene, path, bg).permute(0, 3, 1, 2)
        after = render_rgb(res.scene, path, bg).permute(0, 3, 1, 2)
        metrics["clip"] = clip_metrics(encoder, before, after, args.target, args.instruction)
    video = video_ready()
    report = {"instruction": args.instruction, "target": args.target, "guidance": args.guidance,
              "selected": target.count, "tau": target.tau, "settings": cfg.to_dict(),
              "guidance_settings": guidance.settings(),
              # time_s: the optimisation over all runs (a resumed edit counts its earlier runs, as
              # rounds[-1].time_s does); command_s: this command's wall time.
              "time_s": res.rounds[-1]["time_s"], "command_s": round(command_elapsed_s(), 3),
              "stage_times_s": res.timings_s,
              "gaussians_before": len(scene), "gaussians_after": len(res.scene), "metrics": metrics,
              "rounds": res.rounds}
    if "color" in report["guidance_settings"]:  # recolor: the RGB the instruction / --color resolved to
        report["recolor_rgb"] = [round(float(v), 4) for v in report["guidance_settings"]["color"]]
    from tiger.utils.io import atomic_write

    with atomic_write(out / "edit.json", "w") as fh:
        json.dump(report, fh, indent=2)
    finish_output(out, "edit")
    s = Summary("tiger edit")
    s.add(f"{args.target!r}: {target.count} of {len(scene)} Gaussians edited ({args.guidance}, {args.steps} steps)")
    if "recolor_rgb" in report:
        s.add("colour: RGB " + ", ".join(f"{v:.3f}" for v in report["recolor_rgb"]) + " (0-1)")
    s.add(locality_text(metrics["locality"]))
    s.add(f"edited scene: {out / 'edited.ply'} ({len(res.scene)} Gaussians)")
    s.add(f"pictures: {out / 'before_after.png'}" + (f", video: {video}" if video else ""))
    s.add(f"details: {out / 'edit.json'}")
    s.print()
    return 0
