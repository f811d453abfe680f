"""``handretarget batch``: a GRAB dataset or a manifest of clips onto one or more hands."""

from __future__ import annotations

from .common import _executor, _executor_arguments, _parse_sets, _usage


def add_commands(sub) -> None:
    batch = sub.add_parser(
        "batch", help="retarget many clips (a GRAB folder or a manifest) onto one or more hands, resumably",
        description="Convert every sequence of a GRAB folder (or take the clips a manifest lists), retarget each "
                    "onto every --rig, and write one summary table of every result's figures. Finished outputs "
                    "are skipped, so an interrupted batch is restarted with the same command.")
    src = batch.add_mutually_exclusive_group(required=True)
    src.add_argument("--grab-root", help="a GRAB folder (grab/<subject>/<sequence>.npz, tools/ meshes)")
    src.add_argument("--manifest", help="a file listing clips, one path per line (or a JSON list)")
    batch.add_argument("--mano", help="the MANO right-hand model, with --grab-root")
    batch.add_argument("--mano-left", help="the MANO left-hand model, with --grab-root and --hand left or both")
    batch.add_argument("--hand", choices=("right", "left", "both"), default="right",
                       help="which hands of the GRAB sequences to convert (default right)")
    batch.add_argument("--rig", action="append", required=True,
                       help="a target hand: a file, demo:NAME[@RES] or installed:NAME (repeatable)")
    batch.add_argument("--annotations", help="one annotation file for every clip and hand (default: proposed "
                                             "once per source rig and hand)")
    batch.add_argument("--out", required=True, help="the batch folder (clips/, annotations/, results/, summary)")
    batch.add_argument("--preset", default="default", choices=["default", "paper"], help="configuration preset")
    batch.add_argument("--config", help="TOML configuration applied over the preset")
    batch.add_argument("--set", action="append", metavar="KEY=VALUE", help="configuration override (repeatable)")
    _executor_arguments(batch)
    batch.set_defaults(func=_cmd_batch)


def _cmd_batch(args) -> int:
    from pathlib import Path

    from ..batch import convert_grab, read_manifest, run_batch
    from ..solve.config import load_config

    config = load_config(args.config, args.preset, _parse_sets(args.set))
    out = Path(args.out)
    if args.grab_root:
        hands = ("right", "left") if args.hand == "both" else (args.hand,)
        mano = {"right": args.mano, "left": args.mano_left}
        for hand in hands:
            if not mano[hand]:
                raise _usage(f"converting the {hand} hands needs --{'mano' if hand == 'right' else 'mano-left'}")
        clips = convert_grab(args.grab_root, out / "clips", mano, hands=hands)
    else:
        if args.mano or args.mano_left:
            raise _usage("--mano goes with --grab-root (a manifest's clips are converted already)")
        clips = read_manifest(args.manifest)
    report = run_batch(clips, args.rig, out, config=config, executor=_executor(args), annotations=args.annotations)
    print(f"batch: {report.made} made, {report.skipped} already finished, {report.failed} failed "
          f"({len(clips)} clips x {len(args.rig)} hands)")
    print(f"wrote {report.summary_csv}\nwrote {report.summary_md}")
    return 1 if report.failed else 0
