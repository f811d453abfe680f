"""``handretarget transfer`` and ``handretarget transfer-demo``: contacts onto target hands."""

from __future__ import annotations

import json
from pathlib import Path

from .common import _usage


def add_commands(sub) -> None:
    transfer = sub.add_parser("transfer", help="carry a clip's contacts onto a target hand (report, PNG)")
    transfer.add_argument("--clip", action="append", required=True, help="clip .npz (repeatable)")
    transfer.add_argument("--rig", required=True, help="target rig: a file or demo:NAME[@RESOLUTION]")
    transfer.add_argument("--annotations", required=True, help="annotation JSON")
    transfer.add_argument("--source-rig", help="source rig (default: the one the clip records)")
    transfer.add_argument("--frames", help="comma-separated frames (default: all; the PNG shows 4)")
    transfer.add_argument("--out", help="folder for the report (.json) and the picture (.png)")
    transfer.add_argument("--preset", default="default", choices=["default", "paper"],
                          help="the preset whose contact settings (contacts.keep_patch_size) a retarget would use")
    transfer.set_defaults(func=_cmd_transfer)
    t_demo = sub.add_parser("transfer-demo", help="every demo clip onto every demo hand: shares and spread")
    t_demo.add_argument("--clips", required=True, help="folder of demo clips")
    t_demo.add_argument("--target", action="append", help="only this demo hand (repeatable)")
    t_demo.add_argument("--resolution", type=float, default=0.004, help="target hands' mesh cell size (m)")
    t_demo.add_argument("--every", type=int, default=5, help="use every N-th frame")
    t_demo.add_argument("--preset", default="default", choices=["default", "paper"],
                        help="the preset whose contact settings (contacts.keep_patch_size) a retarget would use")
    t_demo.set_defaults(func=_cmd_transfer_demo)


def _keep_patch_size(args) -> bool:
    """The preset's ``contacts.keep_patch_size``: the transfer a retarget with it would make."""
    from ..solve.config import load_config

    return load_config(None, args.preset).contacts.keep_patch_size


def _transfer_setup(args):
    from ..clip import load_clip
    from ..rig.io import resolve_rig
    from ..transfer.annotations import load_annotations

    target = resolve_rig(args.rig)
    annotations = load_annotations(args.annotations)
    return load_clip, resolve_rig, target, annotations


def _print_transfer_row(name, report):
    dropped_curves = ", ".join(f"{k} {v['dropped']}" for k, v in report["per_curve"].items() if v["dropped"])
    spread = report["spread_ratio_median"]
    print(f"{name:<22} {report['contacts']:>9} {100 * report['transferred_share']:>10.1f}% "
          f"{100 * report['dropped_share']:>8.1f}% {spread if spread is None else round(spread, 2)!s:>8}  "
          f"{dropped_curves or '-'}")


def _cmd_transfer(args) -> int:
    from ..pairing import pair_contacts

    load_clip, resolve_rig, target, annotations = _transfer_setup(args)
    frames = [int(f) for f in args.frames.split(",")] if args.frames else None
    jobs = []
    for clip_path in args.clip:
        clip = load_clip(clip_path)
        jobs.append((Path(clip_path).stem, clip, pair_contacts(clip, frames=frames), clip_path))
    _transfer_table(jobs, resolve_rig(args.source_rig) if args.source_rig else None, target, annotations,
                    Path(args.out) if args.out else None, frames, _keep_patch_size(args))
    return 0


def _transfer_table(jobs, source, target, annotations, out, frames, keep_patch_size: bool) -> None:
    """Transfer each (name, clip, pairs, clip path) onto ``target`` from ``source`` (None: the rig
    each clip records); print a row each; with ``out``, write the report (JSON) and a picture
    (PNG) per clip."""
    from ..inputs import clip_source_rig
    from ..rig.io import resolve_rig
    from ..transfer.clip_transfer import render_transfer, transfer_clip, transfer_report

    print(f"{'clip':<22} {'contacts':>9} {'transferred':>11} {'dropped':>9} {'spread':>8}  dropped by curve")
    for name, clip, pairs, clip_path in jobs:
        src = source or resolve_rig(clip_source_rig(clip, clip_path))
        result = transfer_clip(pairs, src, target, annotations, keep_patch_size=keep_patch_size)
        report = transfer_report(result, src, target)
        _print_transfer_row(name, report)
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            (out / f"{name}.transfer.json").write_text(json.dumps(report, indent=2))
            render_transfer(result, src, target, frames or _contact_rich_frames(pairs, 4), out / f"{name}.transfer.png")


def _contact_rich_frames(pairs, count: int) -> list[int]:
    import numpy as np

    counts = np.diff(pairs.frame_offsets)
    frames = np.nonzero(counts > 0)[0]
    if len(frames) == 0:
        return [0]
    picks = np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)
    return [int(frames[i]) for i in picks]


def _cmd_transfer_demo(args) -> int:
    """Every demo clip onto every demo target with the proposed annotations: shares and spread."""
    from ..clip import load_clip
    from ..pairing import pair_contacts
    from ..inputs import clip_source_rig
    from ..rig.demo_hands import DEMO_HANDS, demo_hand
    from ..rig.io import resolve_rig
    from ..transfer.clip_transfer import transfer_clip, transfer_report
    from ..transfer.propose import propose_annotations

    clips = [c for c in sorted(Path(args.clips).glob("*.npz")) if not c.name.endswith(".pairs.npz")]
    if not clips:
        raise _usage(f"no clips (*.npz) in {args.clips}")
    loaded = [(c.stem, load_clip(c)) for c in clips]
    step = max(1, args.every)
    pairs = {name: pair_contacts(clip, frames=range(0, clip.n_frames, step)) for name, clip in loaded}
    sources = {}
    targets = args.target or list(DEMO_HANDS)
    keep_patch_size = _keep_patch_size(args)
    for target_name in targets:
        target = demo_hand(target_name, resolution=args.resolution)
        print(f"\n== {target_name} ({target.surface.n_vertices} vertices)")
        print(f"{'clip':<22} {'contacts':>9} {'transferred':>11} {'dropped':>9} {'spread':>8}  dropped by curve")
        for (name, clip), path in zip(loaded, clips):
            spec = clip_source_rig(clip, path)
            source = sources.get(spec) or sources.setdefault(spec, resolve_rig(spec))
            annotations = propose_annotations(source, target)
            report = transfer_report(transfer_clip(pairs[name], source, target, annotations,
                                                   keep_patch_size=keep_patch_size), source, target)
            _print_transfer_row(name, report)
    return 0
