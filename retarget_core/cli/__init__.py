"""The ``handretarget`` command line: one module per command group, each registering its own
sub-commands (``add_commands(sub)``). Heavy modules are imported inside each command so that
``--help`` is instant and ``bench`` can pin BLAS to one thread before numpy loads; ``serve`` and
``token`` import the job service (server/) only when they run."""

from __future__ import annotations

import argparse
import os
import sys

from . import annotate, batch, bench, clip, demo, evaluate, keypoints, retarget, rig, service, transfer
from .common import _UsageError

#: The command groups in the order ``handretarget --help`` lists them.
GROUPS = (demo, rig, clip, annotate, transfer, retarget, keypoints, batch, evaluate, bench, service)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="handretarget", description="Contact-aware hand motion retargeting.")
    sub = parser.add_subparsers(dest="command", required=True)
    for group in GROUPS:
        group.add_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "bench":
        # Figures are per core: pin BLAS before numpy is first imported.
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(var, "1")
    from ..errors import InputError

    try:
        return args.func(args)
    except (InputError, _UsageError) as err:
        print(f"handretarget: error: {err}", file=sys.stderr)
        return 2

