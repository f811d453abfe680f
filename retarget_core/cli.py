"""The ``handretarget`` command line. Heavy modules are imported inside each command so that
``--help`` is instant and ``bench`` can pin BLAS to one thread before numpy loads."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def _cmd_rig_demo(args) -> int:
    from .rig.demo_hands import DEMO_HANDS, demo_hand
    from .rig.io import save_rig

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    names = args.hand or list(DEMO_HANDS)
    rows = []
    for name in names:
        rig = demo_hand(name, resolution=args.resolution)
        path = out / f"{name}.usda"
        save_rig(rig, path)
        report = rig.surface.topology()
        rows.append((name, rig.n_dofs, rig.surface.n_vertices, len(rig.surface.faces), report.describe(), path))
    print(f"{'hand':<17} {'DOFs':>4} {'vertices':>9} {'faces':>7}  surface")
    for name, n_dofs, nv, nf, topo, path in rows:
        print(f"{name:<17} {n_dofs:>4} {nv:>9} {nf:>7}  {topo}  -> {path}")
    return 0


def _cmd_rig_info(args) -> int:
    from .rig.io import load_rig
    from .rig.summary import format_rig_info, rig_summary

    rig = load_rig(args.path, wrapper_resolution=args.wrapper_resolution, root_body=args.root_body)
    if args.json:
        print(json.dumps(rig_summary(rig), indent=2))
    else:
        print(format_rig_info(rig, source=str(args.path)))
    return 0


def _cmd_demo(args) -> int:
    """The README's main job. For now: build the demo hand library as USD and summarise it."""
    args.hand = None
    print(f"Building the demo hand library in {args.out} ...")
    return _cmd_rig_demo(args)


def _cmd_bench_kinematics(args) -> int:
    from .benchmarks.kinematics import run_kinematics_benchmark

    figures = run_kinematics_benchmark(hand=args.hand, n_points=args.points, repeats=args.repeats,
                                       resolution=args.resolution)
    if args.json:
        print(json.dumps(figures, indent=2))
        return 0
    print(f"kinematics benchmark: {figures['hand']} ({figures['dofs']} DOFs, {figures['joints']} joints, "
          f"{figures['surface_vertices']} surface vertices), {figures['points']} surface points, one thread")
    for key, label in (
        ("fk", "FK (joint transforms, DOF axes)"),
        ("fk_points_jacobians", "FK + points + point Jacobians"),
        ("fk_points_normals_jacobians", "FK + points, normals + both Jacobians"),
        ("fk_points_vjp", "FK + points vector-Jacobian product"),
        ("skin_all_vertices", "skin all surface vertices"),
    ):
        t = figures[key]
        print(f"  {label:<40} median {t['median_ms']:.3f} ms  (p10 {t['p10_ms']:.3f}, p90 {t['p90_ms']:.3f})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="handretarget", description="Contact-aware hand motion retargeting.")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the main demo job")
    demo.add_argument("--out", default="demo_out", help="output folder")
    demo.add_argument("--resolution", type=float, default=0.002, help="hand mesh cell size in metres")
    demo.set_defaults(func=_cmd_demo)

    rig = sub.add_parser("rig", help="hand rigs")
    rig_sub = rig.add_subparsers(dest="rig_command", required=True)
    rig_demo = rig_sub.add_parser("demo", help="write the demo hand library as USD files")
    rig_demo.add_argument("--out", required=True, help="output folder")
    rig_demo.add_argument("--hand", action="append", help="only this demo hand (repeatable)")
    rig_demo.add_argument("--resolution", type=float, default=0.002, help="mesh cell size in metres")
    rig_demo.set_defaults(func=_cmd_rig_demo)
    rig_info = rig_sub.add_parser("info", help="describe a rig file (USD, URDF or MJCF)")
    rig_info.add_argument("path")
    rig_info.add_argument("--json", action="store_true", help="print JSON instead of text")
    rig_info.add_argument("--root-body", default=None, help="MJCF: the hand's root body")
    rig_info.add_argument("--wrapper-resolution", type=float, default=0.002,
                          help="URDF/MJCF: wrapper surface cell size in metres")
    rig_info.set_defaults(func=_cmd_rig_info)

    bench = sub.add_parser("bench", help="print performance figures")
    bench_sub = bench.add_subparsers(dest="bench_command", required=True)
    kin = bench_sub.add_parser("kinematics", help="FK + Jacobians of many surface points")
    kin.add_argument("--hand", default="source_human")
    kin.add_argument("--points", type=int, default=500)
    kin.add_argument("--repeats", type=int, default=2000)
    kin.add_argument("--resolution", type=float, default=0.002)
    kin.add_argument("--json", action="store_true")
    kin.set_defaults(func=_cmd_bench_kinematics)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "bench":
        # Figures are per core: pin BLAS before numpy is first imported.
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(var, "1")
    from .errors import InputError

    try:
        return args.func(args)
    except InputError as err:
        print(f"handretarget: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
