"""``handretarget retarget-keypoints``: named keypoints (T, K, 3) onto a rig, root included
(:mod:`~retarget_core.solve.keypoints`): animation.json for robot teams, no hand mesh or object."""

from __future__ import annotations


def add_commands(sub) -> None:
    kp = sub.add_parser("retarget-keypoints",
                        help="keypoint positions (T, K, 3) onto a rig, root included -> animation.json")
    kp.add_argument("--rig", required=True, help="target rig: a file, demo:NAME or installed:NAME")
    kp.add_argument("--targets", required=True,
                    help=".npz with positions (T, K, 3) m (NaN: not seen), names (K,): markers of the annotations "
                         "(e.g. IndexFingertip) or joints / links of the rig, and fps")
    kp.add_argument("--out", required=True, help="output folder (animation.json, keypoints.json)")
    kp.add_argument("--annotations", default=None,
                    help="annotation JSON whose markers name keypoints (default: markers proposed for the rig from "
                         "the demo source hand, as `annotate propose` makes them)")
    kp.add_argument("--fps", type=float, default=None, help="frame rate (overrides the file's fps)")
    kp.add_argument("--rate", type=float, default=None, metavar="HZ",
                    help="robot rigs (URDF / MJCF): the control rate of the joint commands (default: --fps)")
    kp.add_argument("--root-body", default=None, help="MJCF rig: the hand's root body")
    kp.set_defaults(func=_cmd_retarget_keypoints)


def _cmd_retarget_keypoints(args) -> int:
    from ..rig.io import resolve_rig
    from ..solve.keypoints import keypoint_sites, load_keypoints, solve_keypoints, write_keypoint_result
    from ..transfer.annotations import load_annotations

    keypoints = load_keypoints(args.targets, args.fps)  # before any rig work: a bad file costs nothing
    rig = resolve_rig(args.rig, **({"root_body": args.root_body} if args.root_body else {}))
    if args.annotations:
        annotations = load_annotations(args.annotations)
    else:
        from ..clip.demo import source_rig
        from ..transfer.propose import propose_annotations

        annotations = propose_annotations(source_rig(), rig)
    sites = keypoint_sites(rig, keypoints.names, annotations)
    solved = solve_keypoints(rig, sites, keypoints)
    paths = write_keypoint_result(args.out, rig, sites, keypoints, solved, rate_hz=args.rate)
    import json

    report = json.loads(paths["keypoints.json"].read_text())
    err = report["error_mm"]
    print(f"{keypoints.n_frames} frames, {len(keypoints.names)} keypoints onto {rig.name}: "
          f"{report['ms_per_frame']:.2f} ms per frame (root included); keypoint error at the delivered curve "
          f"median {err['delivered']['median']:.2f} mm, p95 {err['delivered']['p95']:.2f}, max "
          f"{err['delivered']['max']:.2f} (solved frames: median {err['solved']['median']:.2f})")
    for name, path in paths.items():
        print(f"  {name}: {path}")
    return 0
