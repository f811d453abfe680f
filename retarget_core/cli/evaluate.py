"""``handretarget evaluate``, ``grid`` and ``compare``: metrics of retarget outputs."""

from __future__ import annotations

from pathlib import Path

from .common import _parse_sets


def add_commands(sub) -> None:
    ev = sub.add_parser("evaluate", help="metrics and plots of a retarget output folder (metrics.json, PNGs)")
    ev.add_argument("dir", help="a folder written by handretarget retarget")
    ev.add_argument("--stride", type=int, default=1, help="measure intersections every N-th frame (default 1)")
    ev.add_argument("--self-stride", type=int, help="self intersection every N-th frame (default: --stride)")
    ev.add_argument("--no-render", action="store_true", help="skip the pictures (contact_sheet.png, preview.gif)")
    ev.set_defaults(func=_cmd_evaluate)

    grid = sub.add_parser("grid", help="every demo target x demo clip with our method and both baselines: "
                                       "table (md, csv) and HTML report; reruns reuse finished cells")
    grid.add_argument("--out", required=True, help="output folder")
    grid.add_argument("--target", action="append",
                      help="only this target (repeatable): a demo hand, a rig file or installed:leap / installed:shadow")
    grid.add_argument("--clip", action="append", help="only this demo clip (repeatable)")
    grid.add_argument("--method", action="append", choices=["contacts", "fingertips", "keyvectors"],
                      help="only this method (repeatable)")
    grid.add_argument("--frames", type=int, default=120, help="frames per clip window (default 120)")
    grid.add_argument("--stride", type=int, default=4, help="intersections every N-th frame (default 4)")
    grid.add_argument("--workers", type=int, help="worker processes per retarget")
    grid.add_argument("--set", action="append", metavar="KEY=VALUE",
                      help="configuration override over the default preset (repeatable)")
    grid.set_defaults(func=_cmd_grid)

    cmp_ = sub.add_parser("compare", help="one clip onto two variants of a hand: metrics side by side, "
                                          "per-frame differences, worst frames rendered")
    cmp_.add_argument("--clip", required=True, help="clip .npz")
    cmp_.add_argument("--rig", action="append", required=True, help="a rig file or demo:NAME[@RES] (give two)")
    cmp_.add_argument("--annotations", action="append", help="annotations per rig (default: proposed)")
    cmp_.add_argument("--out", required=True, help="output folder")
    cmp_.add_argument("--frames", type=int, help="only a window of this many frames around the first contact")
    cmp_.add_argument("--stride", type=int, default=4, help="intersections every N-th frame (default 4)")
    cmp_.add_argument("--set", action="append", metavar="KEY=VALUE", help="configuration override (repeatable)")
    cmp_.add_argument("--workers", type=int, help="worker processes per retarget")
    cmp_.set_defaults(func=_cmd_compare)


def _cmd_evaluate(args) -> int:
    import json

    from ..evaluate.report import write_evaluation

    paths = write_evaluation(args.dir, stride=args.stride, self_intersection_stride=args.self_stride,
                             render=not args.no_render)
    doc = json.loads(Path(paths["metrics.json"]).read_text(encoding="utf-8"))
    s = doc["summary"]
    print(f"evaluated {args.dir}: {doc['rig']} ({doc['method']}), {doc['frames']} frames")
    for key, value in s.items():
        print(f"  {key}: {value}")
    for kind, reason in doc["unavailable"].items():
        print(f"  {kind} intersection unavailable: {reason}")
    for path in paths.values():
        print(f"wrote {path}")
    return 0


def _cmd_grid(args) -> int:
    from ..evaluate.grid import run_grid

    from .common import _parse_sets

    paths = run_grid(args.out, targets=args.target, clips=args.clip, methods=args.method or None,
                     frames=args.frames, workers=args.workers, stride=args.stride, overrides=_parse_sets(args.set))
    print(Path(paths["grid.md"]).read_text(encoding="utf-8"))
    for path in paths.values():
        print(f"wrote {path}")
    return 0


def _cmd_compare(args) -> int:
    from ..evaluate.compare import run_compare

    paths = run_compare(args.clip, args.rig, Path(args.out), annotations=args.annotations, workers=args.workers,
                        stride=args.stride, frames=args.frames, overrides=_parse_sets(args.set))
    print(Path(paths["compare.md"]).read_text(encoding="utf-8"))
    for path in paths.values():
        print(f"wrote {path}")
    return 0
