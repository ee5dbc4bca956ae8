"""``tiger eval-lerf``: LERF-OVS localization accuracy (the options are tiger.eval.lerf's)."""
from __future__ import annotations

import argparse
from typing import Sequence

EXAMPLE = ("example: tiger eval-lerf --labels data/lerf_ovs/label --scene figurines=out/figurines.ply "
           "--data figurines=data/lerf_ovs/figurines --clip models/clip-vit-base-patch16 "
           "--out outputs/lerf")


def add_parser(sub) -> None:
    # Listed here for `tiger --help`; main() hands the arguments to tiger.eval.lerf unparsed.
    p = sub.add_parser("eval-lerf", help="LERF-OVS localization accuracy of language scenes",
                       add_help=False, epilog=EXAMPLE)
    p.set_defaults(func=None)


def delegate(argv: Sequence[str]) -> int:
    from tiger.eval import lerf

    parser = lerf.build_parser()
    parser.prog = "tiger eval-lerf"
    parser.epilog = EXAMPLE
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    if any(a in ("-h", "--help") for a in argv):
        parser.print_help()
        return 0
    parser.parse_args(list(argv))  # argparse errors: one line, exit 2
    return int(lerf.main(list(argv)) or 0)
