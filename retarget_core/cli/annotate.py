"""``handretarget annotate propose`` and ``handretarget annotate demo``."""

from __future__ import annotations

from pathlib import Path


def add_commands(sub) -> None:
    annotate = sub.add_parser("annotate", help="annotations (virtual markers, axial curves)")
    annotate_sub = annotate.add_subparsers(dest="annotate_command", required=True)
    a_prop = annotate_sub.add_parser("propose", help="propose annotations from two rigs' skeletons")
    a_prop.add_argument("--source", required=True, help="source rig: a file or demo:NAME[@RESOLUTION]")
    a_prop.add_argument("--target", required=True, help="target rig: a file or demo:NAME[@RESOLUTION]")
    a_prop.add_argument("--out", required=True, help="annotation JSON to write")
    a_prop.set_defaults(func=_cmd_annotate_propose)
    a_demo = annotate_sub.add_parser("demo", help="annotations from the demo source hand to every demo hand")
    a_demo.add_argument("--out", required=True)
    a_demo.add_argument("--resolution", type=float, default=0.004, help="target hands' mesh cell size (m)")
    a_demo.add_argument("--source-resolution", type=float, default=0.004, help="source hand's mesh cell size (m)")
    a_demo.set_defaults(func=_cmd_annotate_demo)


def _cmd_annotate_propose(args) -> int:
    from ..rig.io import resolve_rig
    from ..transfer.annotations import save_annotations
    from ..transfer.propose import propose_annotations

    annotations = propose_annotations(resolve_rig(args.source), resolve_rig(args.target))
    save_annotations(annotations, args.out)
    kept = [c.name for c in annotations.curves if not c.discard]
    dropped = [c.name for c in annotations.curves if c.discard]
    print(f"wrote {args.out}: {len(annotations.markers)} markers, curves {', '.join(kept)}"
          + (f"; discarded {', '.join(dropped)}" if dropped else ""))
    for c in annotations.curves:
        if not c.discard:
            print(f"  {c.name:<9} lambda_a {c.target.lambda_a:<6} lambda_s {c.target.lambda_s.uniform}")
    return 0


def _cmd_annotate_demo(args) -> int:
    from ..rig.demo_hands import DEMO_HANDS
    from ..transfer.annotations import save_annotations
    from ..transfer.propose import propose_annotations
    from ..rig.demo_hands import demo_hand

    out = Path(args.out)
    source = demo_hand("source_human", resolution=args.source_resolution)
    for name in DEMO_HANDS:
        target = demo_hand(name, resolution=args.resolution)
        path = out / f"{name}.json"
        save_annotations(propose_annotations(source, target), path)
        print(f"wrote {path}")
    return 0
