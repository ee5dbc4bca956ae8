"""The defaults chosen by measurement or fixed by a specification, each pinned against its source,
so that changing one is a deliberate act (the source named beside it must change too)."""
from __future__ import annotations

import inspect

from tiger.cli.main import build_parser
from tiger.language.featup import ImplicitConfig
from tiger.recon.config import ReconConfig
from tiger.retrieval import guard
from tiger.retrieval.select import top_cluster_threshold


def _defaults(command: str) -> dict:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")  # the sub-command table
    return {a.dest: a.default for a in sub.choices[command]._actions}


def test_selection_guard_limits_are_those_the_help_states():
    # docs/RETRIEVAL.md and `tiger query --help`: more than half of the scene, or several groups
    # (linked within 5 % of the scene's diagonal, counting groups of >= 10 % of the selection)
    assert (guard.MAX_SHARE, guard.LINK, guard.MIN_GROUP) == (0.5, 0.05, 0.1)


def test_auto_threshold_split_rule():
    # docs/RETRIEVAL.md: a split counts when the density at the cut is <= 0.35 of the lower mode and
    # each side keeps >= 0.2 % of the scores and >= 32 of them (chosen on the demo tabletop)
    sig = inspect.signature(top_cluster_threshold).parameters
    assert {k: sig[k].default for k in ("max_depth", "min_fraction", "min_count")} == \
        {"max_depth": 0.35, "min_fraction": 0.002, "min_count": 32}


def test_implicit_featup_defaults():
    # FeatUp's implicit upsampler drops out at 0.2; the fast fit in bf16 is the default (within
    # tolerance of the reference loop: tests/language/test_featup_implicit.py, docs/LANGUAGE_FEATURES.md)
    cfg = ImplicitConfig()
    assert (cfg.dropout, cfg.method, cfg.precision) == (0.2, "fast", "bf16")


def test_reconstruction_colours_random_points_from_the_views():
    # docs/BENCHMARKS.md, fox reconstruction: colours from the views (with the border masks) gave the
    # fox its held-out PSNR; INRIA's random colours are the alternative
    assert ReconConfig().init_colors == "views"


def test_cli_defaults_of_the_new_commands():
    assert _defaults("embed")["init"] == "lift"  # lifting starts the field (tests/language/test_lift.py)
    view = _defaults("view")
    assert (view["host"], view["port"]) == ("127.0.0.1", 8080)  # loopback unless told otherwise
    for command in ("query", "edit", "delete"):
        assert _defaults(command)["tau"] == "auto", command


def test_reconstruct_background_follows_the_images_and_appearance_stays_opt_in():
    # random backgrounds for opaque photographs (tiger.recon.data.training_background; the fox's
    # held-out PSNR in benchmarks/recon_fox_study.py, docs/BENCHMARKS.md); per-image appearance is a
    # measured candidate, not yet a default: a change here needs its GPU figures
    from tiger.recon.data import training_background

    d = _defaults("reconstruct")
    assert (d["appearance"], d["random_background"]) == (False, None)  # None: decided by the images
    assert training_background([], None)[0] and not training_background(["a.png"], None)[0]
    # the library's trainer (also used to refit edited renders) keeps a fixed background unless told
    assert (ReconConfig().appearance, ReconConfig().random_background) == (False, False)
