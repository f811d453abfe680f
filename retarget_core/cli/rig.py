"""``handretarget rig demo``, ``rig info``, ``rig hand`` and ``rig import``."""

from __future__ import annotations

import json
from pathlib import Path

from .common import _usage


def add_commands(sub) -> None:
    rig = sub.add_parser("rig", help="hand rigs")
    rig_sub = rig.add_subparsers(dest="rig_command", required=True)
    rig_demo = rig_sub.add_parser("demo", help="write the demo hand library as USD files")
    rig_demo.add_argument("--out", required=True, help="output folder")
    rig_demo.add_argument("--hand", action="append", help="only this demo hand (repeatable)")
    rig_demo.add_argument("--resolution", type=float, default=0.002, help="mesh cell size in metres")
    rig_demo.add_argument("--plain", action="store_true",
                          help="write plain UsdSkel (no DOF spec), as another tool's exporter would")
    rig_demo.set_defaults(func=_cmd_rig_demo)
    rig_hand = rig_sub.add_parser("hand", help="what the hand model reads from a rig: palm, fingers, thumb, "
                                                "handedness, parts that are not the hand")
    rig_hand.add_argument("path", help="a rig file or demo:NAME[@RESOLUTION]")
    rig_hand.add_argument("--hand-map", default=None, help="hand mapping JSON that settles what detection cannot")
    rig_hand.add_argument("--json", action="store_true", help="print JSON instead of text")
    rig_hand.set_defaults(func=_cmd_rig_hand)
    rig_info = rig_sub.add_parser("info", help="describe a rig file (USD, URDF or MJCF)")
    rig_info.add_argument("path")
    rig_info.add_argument("--json", action="store_true", help="print JSON instead of text")
    rig_info.add_argument("--root-body", default=None, help="MJCF: the hand's root body")
    rig_info.add_argument("--hand-root", default=None,
                          help="USD: the hand's root joint inside a larger skeleton (default: found)")
    rig_info.add_argument("--wrapper-resolution", type=float, default=0.002,
                          help="URDF/MJCF: wrapper surface cell size in metres")
    rig_info.add_argument("--hand-map", default=None,
                          help="hand mapping JSON, when DOFs are inferred and the hand model cannot tell")
    rig_info.set_defaults(func=_cmd_rig_info)
    rig_import = rig_sub.add_parser(
        "import", help="read any rig (plain UsdSkel, URDF, MJCF) and write it as a rig file with its DOF spec, "
                       "plus its DOF limits as TOML for editing")
    rig_import.add_argument("path", help="the rig file as the other tool wrote it")
    rig_import.add_argument("--out", required=True, help="rig .usda to write")
    rig_import.add_argument("--limits", default=None,
                            help="TOML of DOF limits by joint (as this command writes it) to apply")
    rig_import.add_argument("--limits-out", default=None,
                            help="where to write the DOF limits TOML (default: next to --out, .limits.toml)")
    rig_import.add_argument("--hand-map", default=None, help="hand mapping JSON that settles what detection cannot")
    rig_import.add_argument("--root-body", default=None, help="MJCF: the hand's root body")
    rig_import.add_argument("--hand-root", default=None,
                          help="USD: the hand's root joint inside a larger skeleton (default: found)")
    rig_import.add_argument("--wrapper-resolution", type=float, default=0.002,
                            help="URDF/MJCF: wrapper surface cell size in metres")
    rig_import.set_defaults(func=_cmd_rig_import)
    rig_mirror = rig_sub.add_parser("mirror", help="the mirror image of a rig (a right hand as a left one): "
                                                   "same joints, DOFs and limits, mirrored pose for the same values")
    rig_mirror.add_argument("path", help="a rig file or demo:NAME[@RESOLUTION]")
    rig_mirror.add_argument("--out", required=True, help="rig .usda to write")
    rig_mirror.add_argument("--axis", choices=("x", "y", "z"), default="x",
                            help="the mirror plane's normal, in the rig's frame (default x)")
    rig_mirror.add_argument("--annotations", help="annotations made for a right pair (e.g. MANO_RIGHT -> this rig) ...")
    rig_mirror.add_argument("--annotations-out", help="... written for the mirrored pair (a left clip's MANO hand "
                                                      "onto the mirror)")
    rig_mirror.set_defaults(func=_cmd_rig_mirror)


def _cmd_rig_demo(args) -> int:
    from ..rig.demo_hands import DEMO_HANDS, demo_hand
    from ..rig.io import save_rig

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    names = args.hand or list(DEMO_HANDS)
    rows = []
    for name in names:
        rig = demo_hand(name, resolution=args.resolution)
        path = out / f"{name}.usda"
        if args.plain:
            from ..rig.usd_io import write_rig_usd

            write_rig_usd(rig, path, dof_spec=False)
        else:
            save_rig(rig, path)
        report = rig.surface.topology()
        rows.append((name, "-" if args.plain else rig.n_dofs, rig.surface.n_vertices, len(rig.surface.faces),
                     report.describe(), path))
    print(f"{'hand':<17} {'DOFs':>4} {'vertices':>9} {'faces':>7}  surface")
    for name, n_dofs, nv, nf, topo, path in rows:
        print(f"{name:<17} {n_dofs:>4} {nv:>9} {nf:>7}  {topo}  -> {path}")
    return 0


def _cmd_rig_hand(args) -> int:
    from ..rig.hand_model import hand_model, load_hand_mapping
    from ..rig.io import resolve_rig

    rig = resolve_rig(args.path)
    model = hand_model(rig, load_hand_mapping(args.hand_map) if args.hand_map else None)
    name = rig.joints
    if args.json:
        summary = model.summary()
        summary["palm_joint"] = name[model.palm_joint].name
        summary["fingers"] = {f: [name[j].name for j in js] for f, js in summary["fingers"].items()}
        summary["metacarpals"] = {f: [name[j].name for j in js] for f, js in summary["metacarpals"].items()}
        summary["excluded_joints"] = [name[j].name for j in summary["excluded_joints"]]
        print(json.dumps(summary, indent=2))
        return 0
    print(f"{rig.name}: {model.handedness} hand, palm joint {name[model.palm_joint].name!r}, "
          f"palm {model.palm_length * 1000:.0f} mm long, {model.palm_width * 1000:.0f} mm across the knuckles")
    for f in model.fingers:
        meta = f" (metacarpals {', '.join(name[j].name for j in f.metacarpals)})" if f.metacarpals else ""
        print(f"  {f.name:<7} {', '.join(name[j].name for j in f.joints)}{meta}: "
              f"{f.length * 1000:.0f} mm, girth {f.girth * 1000:.1f} mm")
    if model.excluded_joints:
        print(f"  not the hand: {', '.join(name[j].name for j in model.excluded_joints)}")
    for note in model.notes:
        print(f"  note: {note}")
    return 0


def _cmd_rig_info(args) -> int:
    from ..rig.io import load_rig
    from ..rig.summary import format_rig_info, rig_summary

    rig = load_rig(args.path, wrapper_resolution=args.wrapper_resolution, root_body=args.root_body,
                   mapping=_mapping(args.hand_map), hand_root=args.hand_root)
    if args.json:
        print(json.dumps(rig_summary(rig), indent=2))
    else:
        print(format_rig_info(rig, source=str(args.path)))
    return 0


def _mapping(path):
    from ..rig.hand_model import load_hand_mapping

    return load_hand_mapping(path) if path else None


def _cmd_rig_import(args) -> int:
    from ..files import atomic_path
    from ..rig.dof_limits import apply_limits, limits_toml
    from ..rig.io import load_rig, save_rig

    rig = load_rig(args.path, wrapper_resolution=args.wrapper_resolution, root_body=args.root_body,
                   mapping=_mapping(args.hand_map), hand_root=args.hand_root)
    if args.limits:
        rig = apply_limits(rig, args.limits)
    out = Path(args.out)
    limits_out = Path(args.limits_out) if args.limits_out else out.with_suffix(".limits.toml")
    inferred = "dof_source" in rig.metadata
    if inferred:
        rig.metadata["dof_source"] = (f"inferred by role from {Path(args.path).name} (`handretarget rig import`"
                                      + (f", limits from {Path(args.limits).name}" if args.limits else "")
                                      + f"); limits by joint in {limits_out.name}")
    save_rig(rig, out)
    with atomic_path(limits_out) as tmp:
        Path(tmp).write_text(limits_toml(rig), encoding="utf-8")
    print(f"wrote {out}: {rig.n_joints} joints, {rig.n_dofs} DOFs "
          f"({'inferred by role' if inferred else 'as the file gives them'})")
    print(f"wrote {limits_out}: the DOF limits by joint, to edit and pass back with --limits")
    return 0


def _cmd_rig_mirror(args) -> int:
    from ..rig.io import resolve_rig, save_rig
    from ..rig.mirror import mirror_annotations, mirror_rig
    from ..transfer.annotations import load_annotations, save_annotations

    if bool(args.annotations) != bool(args.annotations_out):
        raise _usage("--annotations and --annotations-out go together")
    rig = resolve_rig(args.path)
    mirrored = mirror_rig(rig, args.axis)
    save_rig(mirrored, args.out)
    print(f"wrote {args.out}: {mirrored.name}, the mirror of {rig.name} across {args.axis}")
    if args.annotations:
        ann = load_annotations(args.annotations)
        save_annotations(mirror_annotations(ann, axis=args.axis, target_rig=mirrored.name), args.annotations_out)
        print(f"wrote {args.annotations_out}: {len(ann.markers)} markers, {len(ann.curves)} curves, for the mirrored pair")
    return 0

