"""``tiger prepare``: photos -> a language-embedded scene in one command (reconstruct, features, embed).

Each stage is the command of the same name run into a folder of DIR; ``DIR/prepare.json`` records
every stage's inputs, time and quality, written atomically after each stage. A re-run skips the
finished stages whose recorded inputs match, continues an interrupted one (the stages resume on
their own: the reconstruction from its checkpoint, the features image by image, the field from its
checkpoint), starts an unfinished stage afresh when its inputs changed, and refuses, naming the
stage and the setting, when a finished stage's inputs changed (--force starts over). The capture
(images and poses) and a ``--scene`` (some Gaussian in some view) are checked before anything is
written. On one GPU the feature stage runs in a second process alongside the reconstruction (it
needs only the images; the two share the GPU, which neither fills), its output in
DIR/features.log; ``--sequential`` runs one stage after the other (the CPU's default). Under ``torchrun`` rank 0 runs
every stage and the other ranks join the feature stage, each extracting its share of the images.
`tiger query/edit/delete/render/view` take DIR for its scene.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Optional

from .common import CliError, add_common, add_skip_missing, device_of, existing, open_dataset
from .features import add_sam_precision

STATE = "prepare.json"
SCENE = "scene_lang.ply"
RECON, FEATURES = "recon", "features"
FEATURES_LOG = "features.log"


def add_parser(sub) -> None:
    p = sub.add_parser(
        "prepare", help="photos -> language-embedded scene: reconstruct, features, embed in one go",
        description="Run `tiger reconstruct` (or start from --scene), `tiger features` and `tiger embed` "
                    "into one folder: DIR/recon (scene.ply, metrics.json), DIR/features, DIR/scene_lang.ply "
                    "and DIR/prepare.json (each stage's inputs, seconds and quality: held-out PSNR, "
                    "Gaussians, field loss). Re-running continues an interrupted stage and skips finished "
                    "ones whose inputs match. Options left out take the stage command's default. "
                    "On one GPU the feature stage runs in a second process alongside the reconstruction "
                    "(log: DIR/features.log; --sequential runs one after the other). "
                    "Under torchrun the feature stage is sharded over the ranks. "
                    "`tiger query DIR ...` (and edit, delete, render, view) use DIR's scene.",
        epilog="example: tiger prepare ../shared/data/fox --out outputs/fox --downscale 2 "
               "--recon-steps 7000 --upsampler jbu\n"
               "         torchrun --nproc_per_node 2 -m tiger.cli.main prepare ../shared/data/fox --out outputs/fox",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", help="dataset folder (COLMAP or transforms.json)")
    add_common(p, models=True)
    add_skip_missing(p)
    p.add_argument("--scene", default=None, metavar="PLY", help="start from this scene (no reconstruction)")
    p.add_argument("--recon-steps", type=int, default=None, help="`tiger reconstruct --steps`")
    p.add_argument("--downscale", type=float, default=None, help="`tiger reconstruct --downscale`")
    p.add_argument("--init-points", type=int, default=None, help="`tiger reconstruct --init-points`")
    p.add_argument("--test-every", type=int, default=None, help="`tiger reconstruct --test-every`")
    p.add_argument("--upsampler", choices=("implicit", "jbu", "bilinear"), default=None,
                   help="`tiger features --upsampler`")
    p.add_argument("--long-side", type=int, default=None, help="`tiger features --long-side`")
    p.add_argument("--clip-long-side", type=int, default=None, help="`tiger features --clip-long-side`")
    p.add_argument("--pca-dim", type=int, default=None, help="`tiger features --pca-dim`")
    p.add_argument("--no-sam", action="store_true", help="`tiger features --no-sam`")
    add_sam_precision(p, passthrough=True)
    p.add_argument("--embed-steps", type=int, default=None, help="`tiger embed --steps`")
    p.add_argument("--init", choices=("lift", "random"), default=None, help="`tiger embed --init`")
    order = p.add_mutually_exclusive_group()
    order.add_argument("--alongside", dest="alongside", action="store_const", const=True, default=None,
                       help="run the feature stage in a second process alongside the reconstruction "
                            "(default on one GPU; its output goes to DIR/features.log)")
    order.add_argument("--sequential", dest="alongside", action="store_const", const=False,
                       help="run the feature stage after the reconstruction (default on the CPU; always "
                            "under torchrun, where the ranks share the feature stage)")
    p.set_defaults(func=run)


def prepared_scene(path: str | Path) -> Path:
    """The scene file a command should read for ``path``: DIR/scene_lang.ply for a prepared folder
    (one holding prepare.json), else ``path`` itself."""
    p = Path(path)
    if p.is_dir() and (p / STATE).is_file():
        scene = p / SCENE
        if not scene.is_file():
            raise CliError(f"{p} is a `tiger prepare` folder whose embed stage has not finished "
                           f"(no {SCENE}); run `tiger prepare` again to continue it")
        return scene
    return p


def _flag_args(pairs: dict[str, Any]) -> list[str]:
    """['--name', 'value', ...] for the options given (None left out: the command's default)."""
    out: list[str] = []
    for flag, value in pairs.items():
        if value is None or value is False:
            continue
        out += [flag] if value is True else [flag, str(value)]
    return out


def _file_id(path: Path) -> str:
    """Content hash of a file (what a later stage read)."""
    h = hashlib.sha1()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


class _State:
    """DIR/prepare.json: per stage {inputs, done, seconds, quality}, saved atomically on each change."""

    def __init__(self, out: Path, force: bool) -> None:
        self.path = out / STATE
        self.data: dict[str, Any] = {"stages": {}}
        if self.path.is_file() and not force:
            try:
                self.data = json.loads(self.path.read_text())
            except json.JSONDecodeError as e:
                raise CliError(f"{self.path} is not valid JSON ({e}); pass --force to start over") from None

    def stage(self, name: str) -> dict[str, Any]:
        stages = self.data["stages"]
        if name not in stages:  # kept in pipeline order, whichever stage starts first
            stages[name] = {}
            order = ("reconstruct", "features", "embed")
            self.data["stages"] = dict(sorted(stages.items(), key=lambda kv: order.index(kv[0])))
        return self.data["stages"][name]

    def save(self) -> None:
        from tiger.utils.io import atomic_write

        with atomic_write(self.path, "w") as fh:
            json.dump(self.data, fh, indent=2)


def _changed(old: dict[str, Any], inputs: dict[str, Any]) -> str:
    """'' when equal, else 'key: old -> new, ...'."""
    keys = sorted(k for k in set(old) | set(inputs) if old.get(k) != inputs.get(k))
    return ", ".join(f"{k}: {old.get(k)!r} -> {inputs.get(k)!r}" for k in keys)


def _begin_stage(state: _State, name: str, index: int, inputs: dict[str, Any], reset: Callable[[dict], None],
                 total: int = 3, note: str = "") -> bool:
    """Whether stage ``name`` is to run. A finished stage with the same inputs is skipped; one with
    other inputs is refused (its output may be what the user wants to keep); an unfinished one with
    other inputs (e.g. a wrong option that made it fail) is started afresh: ``reset(old_inputs)``
    removes what of its partial output the new inputs cannot reuse."""
    record = state.stage(name)
    old = record.get("inputs")
    changed = _changed(old, inputs) if old is not None else ""
    if record.get("done"):
        _refuse_changed(name, record, inputs)
        print(f"[{index}/{total}] {name}: done before ({record.get('seconds', 0):.1f} s), inputs unchanged")
        return False
    if changed:
        print(f"[{index}/{total}] {name}: unfinished run had other inputs ({changed}); starting it afresh")
        reset(old)
        record.clear()
    verb = "continuing" if record.get("inputs") else "running"
    print(f"[{index}/{total}] {name}: {verb}{note}", flush=True)
    record["inputs"] = inputs
    state.save()
    return True


def _finish_stage(state: _State, name: str, started: float, quality: dict) -> None:
    record = state.stage(name)
    record.update(done=True, seconds=record.get("seconds", 0.0) + time.perf_counter() - started, quality=quality)
    state.save()


def _run_stage(state: _State, name: str, index: int, inputs: dict[str, Any], work: Callable[[], dict],
               reset: Callable[[dict], None], total: int = 3) -> None:
    """Run stage ``name`` unless it finished with the same inputs (:func:`_begin_stage`)."""
    if _begin_stage(state, name, index, inputs, reset, total):
        t0 = time.perf_counter()
        _finish_stage(state, name, t0, work())


def _invoke(argv: list[str]) -> None:
    """Run a tiger subcommand in this process; a failure stops prepare with the stage's message."""
    from .common import mark_command_start
    from .main import build_parser

    args = build_parser().parse_args(argv)
    mark_command_start()  # the stage's own "done in" counts from here, not from prepare's start
    code = int(args.func(args) or 0)
    if code:
        raise CliError(f"`tiger {' '.join(argv[:1])}` stopped with exit code {code}")


def _table(state: _State) -> list[str]:
    rows = [("stage", "seconds", "quality")]
    total = 0.0
    for name in ("reconstruct", "features", "embed"):
        rec = state.data["stages"].get(name)
        if not rec:
            continue
        total += float(rec.get("seconds", 0.0))
        q = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                      for k, v in (rec.get("quality") or {}).items() if not isinstance(v, str) or len(v) < 24)
        rows.append((name, f"{rec.get('seconds', 0.0):.1f}", q))
    wall = (state.data.get("result") or {}).get("seconds_this_run")
    overlap = any((state.data["stages"].get(n) or {}).get("quality", {}).get("alongside") for n in ("features",))
    rows.append(("total", f"{total:.1f}", "sum of the stages" if overlap else ""))
    if wall is not None:
        rows.append(("wall clock", f"{float(wall):.1f}", "this run, start to end" + (
            " (features ran alongside the reconstruction)" if overlap else "")))
    w0, w1 = max(len(r[0]) for r in rows), max(len(r[1]) for r in rows)
    return [f"  {a:<{w0}}  {b:>{w1}}  {c}".rstrip() for a, b, c in rows]


def check_scene_seen(scene_file: Path, cameras: list, data: Path) -> None:
    """Refuse a scene none of whose Gaussian centres lies in front of a capture camera and inside
    its picture: nothing could give it a language feature (the scene and the capture are in two
    coordinate frames, e.g. a scene made from another capture)."""
    import torch

    from tiger.scene import GaussianScene

    means = GaussianScene.load_ply(scene_file).means.detach().double()
    seen = torch.zeros(means.shape[0], dtype=torch.bool)
    for cam in cameras:
        uv, depth = cam.project(means)
        seen |= (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        if seen.any():
            return
    raise CliError(f"{scene_file}: none of its {means.shape[0]} Gaussians is in front of any of the {len(cameras)} "
                   f"cameras of {data} and inside its picture; the scene and the capture are not in one "
                   "coordinate frame (was the scene made from another capture?)")


def run(args: argparse.Namespace) -> int:
    """Under torchrun rank 0 runs every stage; the other ranks join only the features stage (each
    extracts its share of the images), told by rank 0 whether it runs and with which arguments."""
    from .features import distributed, on_first_rank

    rank, world = distributed(args.device)
    if rank != 0:
        features_argv = on_first_rank(world, rank, None)
        if features_argv:
            _invoke(features_argv)
        return 0
    ctx: dict[str, Any] = {"world": world}
    features_argv = on_first_rank(world, rank, lambda: _scene_stage(args, ctx))
    return _features_and_embed(args, ctx, features_argv)


def _scene_stage(args: argparse.Namespace, ctx: dict) -> Optional[list[str]]:
    """Checks, the output folder and stage 1 (the scene); fills ``ctx`` and returns the features
    stage's `tiger features` arguments, None when that stage finished before with these inputs."""
    data = existing(args.data, "dataset").resolve()
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CliError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / STATE).is_file() and not args.force:
        raise CliError(f"{out} is not empty and holds no {STATE}; pass --force to prepare into it anyway")
    # the capture's poses and images, and a given scene, checked before anything is written
    cameras = open_dataset(str(data), args.skip_missing).cameras
    if args.scene:
        check_scene_seen(existing(args.scene, "scene file").resolve(), cameras, data)
    if args.force:
        for sub in (RECON, FEATURES):
            shutil.rmtree(out / sub, ignore_errors=True)
        for f in (SCENE, SCENE + ".ckpt.pt", STATE, FEATURES_LOG):
            (out / f).unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    state = _State(out, args.force)
    common = _flag_args({"--device": args.device, "--skip-missing": args.skip_missing})
    t_start = time.perf_counter()

    # 2. the feature maps (they need only the images): decided here, so that under torchrun every
    # rank knows whether it runs; on one GPU started now, alongside stage 1
    feats = out / FEATURES
    f_inputs = {"data": str(data), "models": args.models, "upsampler": args.upsampler,
                "long_side": args.long_side, "clip_long_side": args.clip_long_side, "pca_dim": args.pca_dim,
                "no_sam": args.no_sam, "skip_missing": args.skip_missing}
    if args.sam_precision is not None:  # absent when not given: folders prepared before the option still resume
        f_inputs["sam_precision"] = args.sam_precision
    features_argv = ["features", str(data), "--out", str(feats), *common,
                     *_flag_args({"--models": args.models, "--upsampler": args.upsampler,
                                  "--long-side": args.long_side, "--clip-long-side": args.clip_long_side,
                                  "--pca-dim": args.pca_dim, "--no-sam": args.no_sam,
                                  "--sam-precision": args.sam_precision})]
    ctx.update(data=data, out=out, state=state, common=common, t_start=t_start, feats=feats, f_inputs=f_inputs)
    finished = state.data["stages"].get("features", {})  # read only: the record's order is the stages'
    if finished.get("done"):
        _refuse_changed("features", finished, f_inputs)
    elif ctx["world"] == 1 and (args.alongside if args.alongside is not None
                                else device_of(args.device).type == "cuda"):
        _start_features_alongside(ctx, features_argv)
    try:
        _reconstruct_stage(args, ctx, data, out, state, common)
    except BaseException:
        _stop_features(ctx)
        raise
    return None if state.data["stages"].get("features", {}).get("done") else features_argv


def _start_features_alongside(ctx: dict, features_argv: list[str]) -> None:
    """Start `tiger features` in a second process (its output in DIR/features.log)."""
    out, state = ctx["out"], ctx["state"]
    log_path = out / FEATURES_LOG
    note = f" alongside the reconstruction (a second process; log: {log_path})"
    if not _begin_stage(state, "features", 2, ctx["f_inputs"], lambda old: _reset_features(ctx, old), note=note):
        return
    log = open(log_path, "ab")
    proc = subprocess.Popen([sys.executable, "-m", "tiger.cli.main", *features_argv], stdout=log,
                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    log.close()  # the child holds its own descriptor
    ctx["features_proc"] = (proc, time.perf_counter())


def _stop_features(ctx: dict) -> None:
    """Stop a feature stage running alongside (prepare failed or was interrupted); a re-run resumes it."""
    run = ctx.pop("features_proc", None)
    if run is not None and run[0].poll() is None:
        run[0].terminate()
        try:
            run[0].wait(timeout=30)
        except subprocess.TimeoutExpired:
            run[0].kill()


def _wait_features(ctx: dict) -> None:
    """Wait for the feature stage started alongside and record it; its failure stops prepare with
    the last lines of its log."""
    proc, started = ctx.pop("features_proc")
    print("[2/3] features: waiting for the process started alongside the reconstruction", flush=True)
    try:
        code = proc.wait()
    except BaseException:
        ctx["features_proc"] = (proc, started)
        _stop_features(ctx)
        raise
    log_path = ctx["out"] / FEATURES_LOG
    if code != 0:
        tail = log_path.read_text(errors="replace").strip().splitlines()[-3:] if log_path.is_file() else []
        raise CliError(f"`tiger features` stopped with exit code {code} (log: {log_path}): " + " | ".join(tail))
    _finish_stage(ctx["state"], "features", started, {"maps": len(list((ctx["feats"] / "features").glob("*.pt"))),
                                                      "alongside": "reconstruct"})


def _reset_features(ctx: dict, old: dict) -> None:
    # The per-image cache is keyed by the feature settings (a new PCA size reuses it), not by
    # the models or the images: those start it afresh.
    if any(old.get(k) != ctx["f_inputs"][k] for k in ("data", "models", "skip_missing")):
        shutil.rmtree(ctx["feats"], ignore_errors=True)


def _reconstruct_stage(args: argparse.Namespace, ctx: dict, data: Path, out: Path, state: _State,
                       common: list[str]) -> None:
    """Stage 1: the scene (reconstructed, or given by --scene); sets ``ctx["scene_file"]``."""
    recon = out / RECON
    if args.scene:
        given = existing(args.scene, "scene file").resolve()
        scene_file = given
        _run_stage(state, "reconstruct", 1, {"scene": str(given), "scene_id": _file_id(given)},
                   lambda: {"gaussians": _count_gaussians(given), "source": "--scene"}, lambda old: None)
    else:
        scene_file = recon / "scene.ply"
        inputs = {"data": str(data), "steps": args.recon_steps, "downscale": args.downscale,
                  "init_points": args.init_points, "test_every": args.test_every,
                  "skip_missing": args.skip_missing}

        def reconstruct() -> dict:
            resume = (recon / "checkpoint.pt").is_file()
            # A stage stopped before its first checkpoint leaves only caches: start it afresh.
            fresh = recon.is_dir() and not resume
            _invoke(["reconstruct", str(data), "--out", str(recon), *common,
                     *_flag_args({"--steps": args.recon_steps, "--downscale": args.downscale,
                                  "--init-points": args.init_points, "--test-every": args.test_every,
                                  "--resume": resume, "--force": fresh})])
            metrics = json.loads((recon / "metrics.json").read_text())
            q = {"gaussians": int(metrics["gaussians"])}
            if "psnr" in metrics:
                q["held_out_psnr_db"] = float(metrics["psnr"])
            if "psnr_pixels" in metrics:
                q["psnr_pixels"] = metrics["psnr_pixels"]
            return q

        _run_stage(state, "reconstruct", 1, inputs, reconstruct, lambda old: shutil.rmtree(recon, ignore_errors=True))
    ctx["scene_file"] = scene_file


def _refuse_changed(name: str, record: dict, inputs: dict) -> None:
    changed = _changed(record.get("inputs") or {}, inputs)
    if changed:
        raise CliError(f"stage '{name}' finished with other inputs ({changed}); pass --force to start over")


def _features_and_embed(args: argparse.Namespace, ctx: dict, features_argv: Optional[list[str]]) -> int:
    """Stages 2 and 3 on rank 0, the final table and prepare.json."""
    data, out, state, common, t_start = ctx["data"], ctx["out"], ctx["state"], ctx["common"], ctx["t_start"]
    scene_file, feats, f_inputs = ctx["scene_file"], ctx["feats"], ctx["f_inputs"]

    def features() -> dict:
        _invoke(features_argv)
        return {"maps": len(list((feats / "features").glob("*.pt")))}

    if "features_proc" in ctx:
        _wait_features(ctx)
    else:
        _run_stage(state, "features", 2, f_inputs, features, lambda old: _reset_features(ctx, old))

    # 3. the language field
    lang = out / SCENE
    e_inputs = {"scene_id": _file_id(scene_file), "pca_id": _file_id(feats / "pca.pt"),
                "steps": args.embed_steps, "init": args.init}

    def embed() -> dict:
        ckpt = Path(str(lang) + ".ckpt.pt")
        # an interrupted run left its checkpoint: `tiger embed` continues it. A PLY of this stage not
        # recorded as done is our own unfinished output: it is written again from the checkpoint.
        lang.unlink(missing_ok=True)
        _invoke(["embed", str(scene_file), str(data), "--features", str(feats), "--out", str(lang),
                 *common, *_flag_args({"--steps": args.embed_steps, "--init": args.init})])
        # the loss over every valid pixel of every view at the end, as `tiger embed` recorded it
        # (a training step's own loss is that of a band or a pooled view, not comparable)
        q: dict[str, Any] = {}
        record = Path(str(ckpt) + ".run.json")
        if record.is_file():
            full_loss = json.loads(record.read_text()).get("results", {}).get("full_loss")
            if full_loss is not None:
                q["field_loss"] = float(full_loss)
        return q

    def reset_embed(old: dict) -> None:
        lang.unlink(missing_ok=True)
        Path(str(lang) + ".ckpt.pt").unlink(missing_ok=True)

    _run_stage(state, "embed", 3, e_inputs, embed, reset_embed)

    state.data["result"] = {"scene": str(lang), "features": str(feats),
                            "seconds_this_run": time.perf_counter() - t_start}
    state.save()
    print(f"\ntiger prepare: {lang} (query it with `tiger query {out} TEXT`)")
    for line in _table(state):
        print(line)
    print(f"  -> {state.path}")
    return 0


def _count_gaussians(path: Path) -> Optional[int]:
    from tiger.scene import GaussianScene

    return len(GaussianScene.load_ply(path))
