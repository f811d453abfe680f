"""``handretarget clip demo|info|render|substitute|pair`` and ``handretarget import-grab``."""

from __future__ import annotations

from pathlib import Path

from .common import _UsageError, _usage


def add_commands(sub) -> None:
    clip = sub.add_parser("clip", help="source clips")
    clip_sub = clip.add_subparsers(dest="clip_command", required=True)
    c_demo = clip_sub.add_parser("demo", help="generate the demonstration clips")
    c_demo.add_argument("--out", required=True, help="output folder")
    c_demo.add_argument("--clip", action="append", help="only this clip (repeatable)")
    c_demo.add_argument("--time-scale", type=float, default=1.0, help="shorten (<1) or lengthen the motions")
    c_demo.add_argument("--resolution", type=float, default=0.004, help="source hand mesh cell size in metres")
    c_demo.set_defaults(func=_cmd_clip_demo)
    c_info = clip_sub.add_parser("info", help="validate a clip and describe it")
    c_info.add_argument("path")
    c_info.set_defaults(func=_cmd_clip_info)
    c_render = clip_sub.add_parser("render", help="a PNG strip of a few frames")
    c_render.add_argument("path")
    c_render.add_argument("--out", required=True, help="PNG path")
    c_render.add_argument("--frames", help="comma-separated frame numbers")
    c_render.add_argument("--count", type=int, default=6, help="evenly spaced frames when --frames is not given")
    c_render.add_argument("--view", default="three_quarter", choices=["front", "top", "side", "three_quarter"])
    c_render.add_argument("--size", default="320x320", help="panel size WxH in pixels")
    c_render.set_defaults(func=_cmd_clip_render)
    c_sub = clip_sub.add_parser("substitute", help="replace the clip's object, tracing its contacts onto the new one")
    c_sub.add_argument("clip")
    c_sub.add_argument("--object", required=True, help="a mesh file (OBJ, PLY, STL, ...) or demo:NAME")
    c_sub.add_argument("--scale", help="scale the new object: S or SX,SY,SZ (in its own frame)")
    c_sub.add_argument("--max-distance", type=float, default=0.02, help="metres a contact may be traced (0.02)")
    c_sub.add_argument("--transform", help="place the new object by this 4x4 matrix (16 numbers, row by row, "
                                           "metres; or 'identity': as given) instead of registering it")
    c_sub.add_argument("--translate", help="place it by X,Y,Z metres (after --rotate) instead of registering it")
    c_sub.add_argument("--rotate", help="place it by RX,RY,RZ degrees (XYZ Euler angles) instead of registering it")
    c_sub.add_argument("--min-share", type=float, default=0.8,
                       help="refuse when a smaller share of the contacts reaches the new object (0.8)")
    c_sub.add_argument("--allow-intersection", action="store_true",
                       help="write the clip even when the source hand lies inside the new object")
    c_sub.add_argument("--out", required=True, help="the new clip .npz")
    c_sub.set_defaults(func=_cmd_clip_substitute)
    c_pair = clip_sub.add_parser("pair", help="dense contact pairing: report paired and discarded contacts")
    c_pair.add_argument("paths", nargs="+")
    c_pair.add_argument("--epsilon", type=float, default=0.015, help="largest pair distance in metres")
    c_pair.add_argument("--per-frame", action="store_true", help="print counts for every frame with contacts")
    c_pair.add_argument("--out", help="folder for the pairs (.pairs.npz)")
    c_pair.set_defaults(func=_cmd_clip_pair)

    grab = sub.add_parser("import-grab", help="convert a GRAB sequence into a clip")
    grab.add_argument("sequence", help="GRAB sequence .npz")
    grab.add_argument("--mano", help="the MANO right-hand model (MANO_RIGHT.pkl)")
    grab.add_argument("--mano-left", help="the MANO left-hand model (MANO_LEFT.pkl), for --hand left or both")
    grab.add_argument("--hand", choices=("right", "left", "both"), default="right",
                      help="which hand to import (both: two clips sharing the object, OUT's name + _right/_left)")
    grab.add_argument("--out", required=True,
                      help="clip .npz to write; its MANO source rig is written beside it (<name>.source_rig.usda)")
    grab.add_argument("--object-mesh", help="the object's mesh (default: found under --grab-root)")
    grab.add_argument("--table-mesh", help="the table's mesh (default: found under --grab-root)")
    grab.add_argument("--vtemp", help="the subject's hand template mesh (778 vertices; default: found under "
                                     "--grab-root; with --hand both it is the right hand's)")
    grab.add_argument("--vtemp-left", help="the subject's left-hand template, with --hand both")
    grab.add_argument("--grab-root", help="GRAB's root folder, to resolve the paths stored in the sequence")
    grab.set_defaults(func=_cmd_import_grab)


def _cmd_clip_demo(args) -> int:
    import numpy as np

    from ..clip.demo import DEMO_CLIPS, make_demo_clip, source_rig

    out = Path(args.out)
    names = args.clip or list(DEMO_CLIPS)
    unknown = [n for n in names if n not in DEMO_CLIPS]
    if unknown:
        raise _usage(f"unknown demo clip {unknown[0]!r}; known: {', '.join(DEMO_CLIPS)}")
    rig = source_rig(args.resolution)
    print(f"{'clip':<18} {'object':<7} {'frames':>6} {'contact frames':>14} {'contacts/frame':>14}  motion")
    for name in names:
        clip = make_demo_clip(name, time_scale=args.time_scale, resolution=args.resolution, rig=rig)
        clip.save(out / f"{name}.npz")
        counts = (clip.contact_labels > 0).sum(axis=1)
        median = int(np.median(counts[counts > 0])) if (counts > 0).any() else 0
        print(f"{name:<18} {clip.object_name:<7} {clip.n_frames:>6} {int((counts > 0).sum()):>14} {median:>14}  {clip.motion}")
    print(f"wrote {len(names)} clips to {out}")
    return 0


def _cmd_clip_info(args) -> int:
    from ..clip import load_clip

    clip = load_clip(args.path)
    counts = (clip.contact_labels > 0).sum(axis=1)
    print(f"clip {args.path}: valid")
    print(f"  {clip.n_frames} frames at {clip.fps:g} fps ({clip.duration:.2f} s), source {clip.source or '-'}")
    print(f"  hand: {clip.hand_vertices.shape[1]} vertices, {len(clip.hand_faces)} faces; markers: {len(clip.marker_names)}")
    print(f"  object {clip.object_name or '-'}: {len(clip.object_vertices)} vertices, {len(clip.object_faces)} faces")
    print(f"  contacts: {int((counts > 0).sum())} frames with contacts, up to {int(counts.max())} per frame")
    print(f"  table: {'yes' if clip.has_table else 'no'}; ground-truth DOFs: {len(clip.dof_names) or 'no'}")
    return 0


def _cmd_clip_render(args) -> int:
    import numpy as np

    from ..clip import load_clip
    from ..render import render_clip_strip

    clip = load_clip(args.path)
    if args.frames:
        frames = [int(f) for f in args.frames.split(",")]
    else:
        frames = np.linspace(0, clip.n_frames - 1, args.count).round().astype(int).tolist()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    path = render_clip_strip(clip, frames, args.out, size=size, view=args.view)
    print(f"wrote {path} (frames {', '.join(map(str, frames))})")
    return 0


def _cmd_clip_substitute(args) -> int:
    import numpy as np

    from ..clip import load_clip
    from ..clip.substitute import substitute_object

    clip = load_clip(args.clip)
    if args.object.startswith("demo:"):
        from ..clip.objects import OBJECT_NAMES, make_object

        name = args.object[len("demo:"):]
        if name not in OBJECT_NAMES:
            raise _UsageError(f"unknown demo object {name!r} (known: {', '.join(OBJECT_NAMES)})")
        obj = make_object(name)
        vertices, faces = obj.vertices, obj.faces
    else:
        from ..mesh.io import load_mesh_file

        vertices, faces = load_mesh_file(args.object, "the new object's", "object mesh")
        name = Path(args.object).stem
    if args.scale:
        try:
            scale = [float(x) for x in args.scale.split(",")]
        except ValueError:
            raise _UsageError(f"--scale must be one or three numbers, got {args.scale!r}") from None
        if len(scale) not in (1, 3) or min(scale) <= 0:
            raise _UsageError(f"--scale must be one or three positive numbers, got {args.scale!r}")
        vertices = np.asarray(vertices, dtype=float) * np.array(scale if len(scale) == 3 else scale * 3)
    transform = _placement(args)
    new, report = substitute_object(clip, vertices, faces, name=name, max_distance=args.max_distance,
                                    register=transform is None, transform=transform, min_share=args.min_share,
                                    allow_intersection=args.allow_intersection)
    for line in report["repairs"]:
        print(f"repaired the new object: {line}")
    if "residual_mm" in report:
        print(f"registered the new object onto {clip.object_name}: RMS {report['residual_mm']:.2f} mm over the "
              f"{report['labelled_vertices']} contact-region vertices ({report['surface_residual_mm']:.2f} mm over "
              "its whole surface)")
    print("placement (new object -> old object's frame, metres):")
    for row in report["transform"]:
        print("  " + " ".join(f"{x:10.6f}" for x in row))
    depth = max(report["hand_depth_mm"], default=0.0)
    if depth > 0:
        print(f"the source hand goes up to {depth:.2f} mm into the new object")
    print(f"{args.clip}: object {clip.object_name} -> {new.object_name}; labelled vertices {report['labelled_vertices']}, "
          f"traced {report['traced']} ({100 * report['share']:.1f} %), dropped {report['dropped']} "
          f"(farther than {args.max_distance * 100:g} cm)")
    new.save(args.out)
    print(f"wrote {args.out}")
    return 0


def _placement(args):
    """The 4x4 placing the new object from --transform / --translate / --rotate; None:
    register it."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    if args.transform and (args.translate or args.rotate):
        raise _UsageError("give --transform or --translate/--rotate, not both")
    if args.transform:
        if args.transform.strip().lower() == "identity":
            return np.eye(4)
        values = _numbers(args.transform, 16, "--transform")
        return np.array(values).reshape(4, 4)
    if not (args.translate or args.rotate):
        return None
    m = np.eye(4)
    if args.rotate:
        m[:3, :3] = Rotation.from_euler("xyz", _numbers(args.rotate, 3, "--rotate"), degrees=True).as_matrix()
    if args.translate:
        m[:3, 3] = _numbers(args.translate, 3, "--translate")
    return m


def _numbers(text: str, count: int, flag: str) -> list[float]:
    import numpy as np

    try:
        values = [float(x) for x in text.replace(",", " ").split()]
    except ValueError:
        raise _UsageError(f"{flag} takes {count} numbers, got {text!r}") from None
    if len(values) != count or not all(np.isfinite(values)):
        raise _UsageError(f"{flag} takes {count} finite numbers, got {text!r}")
    return values


def _cmd_clip_pair(args) -> int:
    import numpy as np

    from ..clip import load_clip
    from ..pairing import pair_contacts

    print(f"{'clip':<28} {'contacts':>9} {'paired':>8} {'miss':>6} {'too far':>7} {'discarded':>9} "
          f"{'gap median':>10} {'gap p90':>8}")
    worst_discard, worst_median = 0.0, 0.0
    for path in args.paths:
        clip = load_clip(path)
        pairs = pair_contacts(clip, epsilon=args.epsilon)
        s = pairs.summary()
        median = s["gap_median_mm"] if s["gap_median_mm"] is not None else float("nan")
        p90 = s["gap_p90_mm"] if s["gap_p90_mm"] is not None else float("nan")
        print(f"{Path(path).name:<28} {s['contacts']:>9} {s['paired']:>8} {s['miss']:>6} {s['too_far']:>7} "
              f"{100 * s['discarded_fraction']:>8.1f}% {median:>8.2f}mm {p90:>6.2f}mm")
        worst_discard = max(worst_discard, s["discarded_fraction"])
        worst_median = max(worst_median, median if np.isfinite(median) else 0.0)
        if args.per_frame:
            for f in range(clip.n_frames):
                if pairs.n_contacts[f]:
                    print(f"    frame {f}: {pairs.n_contacts[f]} contacts, {pairs.n_paired[f]} paired, "
                          f"{pairs.n_miss[f]} miss, {pairs.n_too_far[f]} too far, {pairs.n_inverted[f]} inverted")
        if args.out:
            out = Path(args.out) / (Path(path).stem + ".pairs.npz")
            pairs.save(out)
    print(f"worst discarded fraction {100 * worst_discard:.1f}%, worst median gap {worst_median:.2f} mm")
    return 0


def _cmd_import_grab(args) -> int:
    from ..clip.grab import import_grab_hand, save_grab_hand
    from ..errors import InputError

    hands = ("right", "left") if args.hand == "both" else (args.hand,)
    models = {"right": args.mano, "left": args.mano_left}
    for hand in hands:
        if not models[hand]:
            raise InputError(f"the {hand} hand needs its MANO model: pass --{'mano' if hand == 'right' else 'mano-left'} "
                             f"MANO_{hand.upper()}.pkl", element="mano" if hand == "right" else "mano_left")
    out = Path(args.out)
    for hand in hands:
        vtemp = args.vtemp_left if hand == "left" and args.hand == "both" else args.vtemp
        imported = import_grab_hand(args.sequence, models[hand], hand=hand, object_mesh=args.object_mesh,
                                    table_mesh=args.table_mesh, vtemp=vtemp, grab_root=args.grab_root)
        path = out if len(hands) == 1 else out.with_name(f"{out.name.removesuffix('.npz')}_{hand}.npz")
        clip_path, rig_path = save_grab_hand(imported, path)
        clip = imported.clip
        counts = (clip.contact_labels > 0).sum(axis=1)
        print(f"wrote {clip_path}: {clip.n_frames} frames at {clip.fps:g} fps, object {clip.object_name or '-'}, "
              f"{int((counts > 0).sum())} frames with {hand}-hand contacts ({clip.source})")
        print(f"wrote {rig_path}: its MANO source rig ({'subject template' if imported.template is not None else 'MANO mean template'})")
        if imported.template is None:
            print(f"  note: the subject's {hand}-hand template (GRAB's tools/subject_meshes/<gender>/<subject>_"
                  f"{'rhand' if hand == 'right' else 'lhand'}.ply) was not found: the hand is MANO's mean shape, not "
                  "the subject's; pass --grab-root or --vtemp")
        if not counts.any():
            print(f"  note: the {hand} hand touches the object in no frame: a retarget follows its markers only")
    return 0
