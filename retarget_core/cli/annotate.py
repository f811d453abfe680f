"""``handretarget annotate propose``, ``handretarget annotate remap`` and ``handretarget annotate demo``."""

from __future__ import annotations

from pathlib import Path


def add_commands(sub) -> None:
    annotate = sub.add_parser("annotate", help="annotations (virtual markers, axial curves)")
    annotate_sub = annotate.add_subparsers(dest="annotate_command", required=True)
    a_prop = annotate_sub.add_parser("propose", help="propose annotations from two rigs' skeletons")
    a_prop.add_argument("--source", required=True,
                        help="source rig: a file, demo:NAME[@RESOLUTION], or a clip (.npz: the rig it records, "
                             "e.g. a GRAB import's MANO hand)")
    a_prop.add_argument("--target", required=True, help="target rig: a file or demo:NAME[@RESOLUTION]")
    a_prop.add_argument("--out", required=True, help="annotation JSON to write")
    a_prop.add_argument("--source-hand-map", default=None,
                        help="hand mapping JSON for the source rig (palm joint, finger joints, handedness), "
                             "when its hand model cannot tell")
    a_prop.add_argument("--hand-map", default=None, help="hand mapping JSON for the target rig")
    a_prop.add_argument("--root-body", default=None, help="MJCF target: the hand's root body")
    a_prop.add_argument("--hand-root", default=None,
                        help="plain USD target inside a larger skeleton: the hand's root joint (default: found)")
    a_prop.add_argument("--png", nargs="?", const="", default=None, metavar="FILE",
                        help="also draw both hands with the proposed curves and markers, seen from the palm "
                             "and the back, to FILE (without FILE: next to the JSON, same name, .png)")
    a_prop.set_defaults(func=_cmd_annotate_propose)
    a_remap = annotate_sub.add_parser(
        "remap", help="carry annotations onto edited rig meshes (closest surface point), or give them positions",
        description="Carry annotations onto the rigs' current meshes: a side whose mesh changed since the "
                    "annotations were made has every point moved to the closest point of the new surface (the "
                    "annotations need positions: version 2). Run against the rigs the annotations were made for, "
                    "it writes them with positions, so that they survive later mesh edits.")
    a_remap.add_argument("annotations", metavar="ANNOTATIONS", help="annotation JSON to carry over")
    a_remap.add_argument("--source", required=True, help="source rig now: a file or demo:NAME[@RESOLUTION]")
    a_remap.add_argument("--target", required=True, help="target rig now: a file or demo:NAME[@RESOLUTION]")
    a_remap.add_argument("--out", required=True, help="annotation JSON to write (version 2, with positions)")
    a_remap.add_argument("--max-displacement-mm", type=float, default=3.0, metavar="MM",
                         help="refuse when a point moves further than this (default 3)")
    a_remap.set_defaults(func=_cmd_annotate_remap)
    a_demo = annotate_sub.add_parser("demo", help="annotations from the demo source hand to every demo hand")
    a_demo.add_argument("--out", required=True)
    a_demo.add_argument("--resolution", type=float, default=0.004, help="target hands' mesh cell size (m)")
    a_demo.add_argument("--source-resolution", type=float, default=0.004, help="source hand's mesh cell size (m)")
    a_demo.add_argument("--hand", action="append", help="only this demo hand (repeatable; default: all)")
    a_demo.set_defaults(func=_cmd_annotate_demo)


def _cmd_annotate_propose(args) -> int:
    from ..rig.hand_model import load_hand_mapping
    from ..rig.io import resolve_rig
    from ..transfer.annotations import save_annotations, with_positions
    from ..transfer.propose import propose

    source_map = load_hand_mapping(args.source_hand_map) if args.source_hand_map else None
    target_map = load_hand_mapping(args.hand_map) if args.hand_map else None
    source = resolve_rig(_source_spec(args.source), mapping=source_map)
    target = resolve_rig(args.target, mapping=target_map, root_body=args.root_body, hand_root=args.hand_root)
    proposal = propose(source, target, source_mapping=source_map, target_mapping=target_map)
    annotations = proposal.annotations
    save_annotations(with_positions(annotations, source, target), args.out)  # positions: survive mesh edits
    kept = [c.name for c in annotations.curves if not c.discard]
    dropped = [c.name for c in annotations.curves if c.discard]
    print(f"wrote {args.out}: {len(annotations.markers)} markers, curves {', '.join(kept)}"
          + (f"; discarded {', '.join(dropped)}" if dropped else ""))
    for side, model in (("source", proposal.source_model), ("target", proposal.target_model)):
        print(f"  {side} {model.rig_name}: {model.handedness} hand, fingers {', '.join(model.finger_names)}")
    for c in annotations.curves:
        if not c.discard:
            print(f"  {c.name:<9} lambda_a {c.target.lambda_a:<6} lambda_s {c.target.lambda_s.uniform}")
    for message in proposal.messages():
        print(f"  note: {message}")
    if args.png is not None:
        from ..render.annotation_view import draw_proposal

        png = Path(args.png) if args.png else Path(args.out).with_suffix(".png")
        draw_proposal(proposal, png, source_rig=source, target_rig=target)
        print(f"wrote {png}")
    return 0


def _source_spec(spec: str) -> str:
    """A source rig spec, or for a clip (.npz) the rig it records."""
    if str(spec).lower().endswith(".npz"):
        from ..clip import load_clip
        from ..inputs import clip_source_rig

        return clip_source_rig(load_clip(spec), spec)
    return spec


def _cmd_annotate_remap(args) -> int:
    from ..rig.io import resolve_rig
    from ..transfer.annotations import load_annotations, remap_to_meshes, save_annotations, with_positions

    annotations = load_annotations(args.annotations)
    source, target = resolve_rig(args.source), resolve_rig(args.target)
    remapped, report = remap_to_meshes(annotations, source, target, max_displacement=args.max_displacement_mm / 1000.0,
                                       source=str(args.annotations))
    save_annotations(with_positions(remapped, source, target), args.out)
    for line in report.lines():
        print(f"  {line}")
    print(f"wrote {args.out}" + ("" if report.changed else " (meshes unchanged: positions added)"))
    return 0


def _cmd_annotate_demo(args) -> int:
    from ..rig.demo_hands import DEMO_HANDS
    from ..transfer.annotations import save_annotations
    from ..transfer.propose import propose_annotations
    from ..rig.demo_hands import demo_hand

    out = Path(args.out)
    source = demo_hand("source_human", resolution=args.source_resolution)
    for name in args.hand or DEMO_HANDS:
        target = demo_hand(name, resolution=args.resolution)
        path = out / f"{name}.json"
        save_annotations(propose_annotations(source, target), path)
        print(f"wrote {path}")
    return 0
