"""``handretarget retarget``: one clip onto one rig."""

from __future__ import annotations

import json
from pathlib import Path

from .common import _executor, _executor_arguments, _fmt_mm, _parse_sets, _run_retarget


def add_commands(sub) -> None:
    ret = sub.add_parser("retarget", help="retarget a clip onto a rig: USD animation, result JSON, joint JSON")
    ret.add_argument("--clip", required=True, help="clip .npz")
    ret.add_argument("--rig", required=True, help="target rig: a file or demo:NAME[@RESOLUTION]")
    ret.add_argument("--annotations", required=True, help="annotation JSON (source hand -> this rig)")
    ret.add_argument("--out", required=True, help="output folder")
    ret.add_argument("--source-rig", help="source rig (default: the one the clip records, else the demo source hand)")
    ret.add_argument("--preset", default="default", choices=["default", "paper"], help="configuration preset")
    ret.add_argument("--config", help="TOML configuration applied over the preset")
    ret.add_argument("--set", action="append", metavar="KEY=VALUE",
                     help="configuration override, e.g. solver.maxeval=50 (repeatable)")
    ret.add_argument("--frames", metavar="START:END", help="retarget only these frames of the clip (end excluded)")
    ret.add_argument("--root-body", default=None, help="MJCF target: the hand's root body (a forearm or mount "
                                                       "above it is left out)")
    ret.add_argument("--hand-root", default=None,
                     help="plain USD target inside a larger skeleton: the hand's root joint (default: found)")
    ret.add_argument("--hand-map", default=None,
                     help="hand mapping JSON for the target, when its DOFs are inferred and the hand model cannot tell")
    ret.add_argument("--max-annotation-displacement-mm", type=float, default=3.0, metavar="MM",
                     help="annotations with positions made for an earlier version of a rig's mesh are carried onto "
                          "its current mesh (closest surface point); refuse when a point moves further (default 3)")
    ret.add_argument("--rate", type=float, default=None, metavar="HZ",
                     help="robot rigs (URDF / MJCF): the control rate of the joint commands in animation.json "
                          "(default: the clip's frame rate)")
    ret.add_argument("--no-pictures", action="store_true",
                     help="skip the contact sheet and animated preview (contact_sheet.png, preview.gif)")
    _executor_arguments(ret)
    ret.set_defaults(func=_cmd_retarget)


def _cmd_retarget(args) -> int:
    from ..export import read_animation_json
    from ..inputs import load_inputs
    from ..solve.config import load_config

    config = load_config(args.config, args.preset, _parse_sets(args.set))
    from ..rig.hand_model import load_hand_mapping

    inputs = load_inputs(args.clip, args.rig, args.annotations, source_rig=args.source_rig, frames=args.frames,
                         annotation_max_displacement=args.max_annotation_displacement_mm / 1000.0,
                         target_options={"root_body": args.root_body, "hand_root": args.hand_root,
                                         "mapping": load_hand_mapping(args.hand_map) if args.hand_map else None})
    rig_path = None if str(args.rig).startswith("demo:") else args.rig
    result, paths = _run_retarget(inputs, config, _executor(args), Path(args.out), rig_path,
                                  control_rate_hz=args.rate, pictures=not args.no_pictures)
    s = result.summary
    print(f"retargeted {args.clip} (frames {result.frames[0]}:{result.frames[1]}) onto {inputs.target_rig.name}: "
          f"{s['frames']} frames, {s['dofs']} DOFs, {s['control_points'] or 'no'} control points per DOF")
    print("  seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in result.timings.items()))
    print(f"  at the {s['figures_at']}: median contact distance {_fmt_mm(s['contact_distance_median_mm'])} mm over "
          f"{s['contact_frames']} contact frames; marker error {_fmt_mm(s['marker_error_median_mm'])} mm")
    print(f"  at the solved frames: median contact distance {_fmt_mm(s['solved_contact_distance_median_mm'])} mm; "
          f"marker error {_fmt_mm(s['solved_marker_error_median_mm'])} mm; failed frames {s['failed_frames']}; "
          f"unresolved entries {s['unresolved_entries']}; fit failures {s['fit_failures']}")
    if s.get("unmapped_contacts"):
        print(f"  note: {s['unmapped_contacts']} source contacts lie where no log-map chart of the source hand is "
              "one-to-one (a mesh too coarse there for geodesics, e.g. a fingertip of a few triangles): dropped, "
              "not guessed; `handretarget transfer` shows them per curve")
    if s.get("penetration_term", "").startswith("on ("):
        print(f"  note: penetration term {s['penetration_term']}")
    for line in result.provenance.get("annotation_remap", {}).get("lines", []):
        print(f"  annotations: {line}")
    for key, v in result.unused_settings.items():
        print(f"  note: {key} = {v['value']!r} is not used: {v['why']}")
    robot = read_animation_json(paths["animation.json"]).get("robot")
    if robot:
        over = robot["velocity_exceeded"]
        print(f"  robot: {len(robot['joints'])} joints in the file's order at {robot['rate_hz']:g} Hz; velocity "
              f"limits {robot['velocity_limits']}" + (f", exceeded on {', '.join(over)} (animation.json robot.velocity "
                                                      "lists when)" if over else ", all kept"))
    if "pictures.json" in paths:
        pictures = json.loads(Path(paths["pictures.json"]).read_text(encoding="utf-8"))
        share = pictures["contacts_unoccluded_share"]
        views = " and ".join(str(v["direction"]) for v in pictures["views"])
        print(f"  pictures: seen from {views} (towards the eye), "
              + (f"{100 * share:.0f} % of the sheet's {pictures['contacts_in_sheet']} target contact points unoccluded"
                 if pictures["contacts_in_sheet"] else "no contacts in the sheet's frames"))
    for path in paths.values():
        print(f"wrote {path}")
    return 0
