"""``handretarget demo``: the README's main job, from the demo hands to the retarget summary."""

from __future__ import annotations

from pathlib import Path

from .common import _UsageError, _fmt_mm, _run_retarget
from .transfer import _transfer_table


def add_commands(sub) -> None:
    demo = sub.add_parser("demo", help="run the main demo job")
    demo.add_argument("--out", default="demo_out", help="output folder")
    demo.add_argument("--resolution", type=float, default=0.003, help="demo hands' mesh cell size in metres")
    demo.add_argument("--clip", action="append", help="only this demo clip (repeatable)")
    demo.add_argument("--time-scale", type=float, default=1.0, help="shorten (<1) the demo clips")
    demo.add_argument("--hand", action="append", help="only this demo hand (repeatable; default: every one)")
    demo.set_defaults(func=_cmd_demo)


def _cmd_demo(args) -> int:
    """The README's main job: the demo hand library (USD), the demonstration clips, their
    dense contact pairing, a PNG strip of each clip, annotations from the source hand to every
    demo hand, the contact transfer onto each (report and pictures) and the retarget of one second
    of a clip onto every demo hand (USD animation, result and joint JSON, summary table)."""
    out = Path(args.out)
    print(f"== demo hand library -> {out / 'rigs'}")
    from ..rig.demo_hands import DEMO_HANDS

    unknown = sorted(set(args.hand or ()) - set(DEMO_HANDS))
    if unknown:
        raise _UsageError(f"no demo hand {', '.join(unknown)} (the demo hands: {', '.join(DEMO_HANDS)})")
    hands = args.hand or list(DEMO_HANDS)
    only = [a for h in hands for a in ("--hand", h)]
    _step("rig", "demo", "--out", out / "rigs", "--resolution", args.resolution, *only)
    print(f"\n== demonstration clips -> {out / 'clips'}")
    _step("clip", "demo", "--out", out / "clips", "--time-scale", args.time_scale, "--resolution", 0.004,
          *[a for c in args.clip or () for a in ("--clip", c)])
    clips = [c for c in sorted((out / "clips").glob("*.npz")) if not c.name.endswith(".pairs.npz")]
    print("\n== dense contact pairing")
    _step("clip", "pair", *clips, "--epsilon", 0.015, "--out", out / "clips")
    print("\n== renders")
    for path in clips:
        _step("clip", "render", path, "--out", path.with_suffix(".png"), "--count", 6, "--view", "three_quarter",
              "--size", "320x320")
    print(f"\n== annotations -> {out / 'annotations'}")
    _step("annotate", "demo", "--out", out / "annotations", "--resolution", args.resolution,
          "--source-resolution", 0.004, *only)
    print(f"\n== contact transfer onto every demo hand -> {out / 'transfer'}")
    from ..clip import load_clip
    from ..pairing import load_contact_pairs
    from ..rig.demo_hands import demo_hand
    from ..transfer.annotations import load_annotations

    jobs = [(c.stem, load_clip(c), load_contact_pairs(c.with_name(c.stem + ".pairs.npz")), c) for c in clips]
    from ..solve.config import load_config

    keep_patch_size = load_config(None, "default").contacts.keep_patch_size  # the transfer the retarget makes
    for name in hands:
        print(f"-- {name}")
        _transfer_table(jobs, None, demo_hand(name, resolution=args.resolution),
                        load_annotations(out / "annotations" / f"{name}.json"), out / "transfer" / name, None,
                        keep_patch_size)
    print(f"\n== retarget one second of {RETARGET_DEMO_CLIP} onto every demo hand -> {out / 'retarget'}")
    _retarget_demo(out, args.resolution, args.time_scale, hands)
    return 0


def _step(*argv) -> None:
    """Run one ``handretarget`` sub-command as the command line would (its parser's defaults:
    a step never misses an option added to it later); an error stops the demo."""
    from . import build_parser

    args = build_parser().parse_args([str(a) for a in argv])
    code = args.func(args)
    if code:
        raise SystemExit(f"handretarget demo: the step `handretarget {' '.join(map(str, argv))}` failed ({code})")


#: The demo's retarget stage: one second (RETARGET_DEMO_FRAMES at 120 fps) of this clip at its
#: natural speed, from half a second before the first contact (reach, grasp, lift). A shortened
#: clip (time_scale < 1) would move faster than the acceleration threshold E_acc allows.
RETARGET_DEMO_CLIP = "bottle_pick_place"
RETARGET_DEMO_FRAMES = 120


def _retarget_demo(out: Path, resolution: float, time_scale: float, hands) -> None:
    """Retarget a short window of the demo clip onto each demo hand in ``hands`` with the proposed
    annotations (``out/annotations``) and the default preset; write ``out/retarget/<hand>/``
    and a summary table (``out/retarget/summary.md``)."""
    from ..clip import load_clip
    from ..clip.demo import grasp_window, make_demo_clip, source_rig
    from ..execute import Executor, default_workers
    from ..inputs import RunInputs
    from ..pairing import pair_contacts
    from ..rig.demo_hands import demo_hand
    from ..solve.config import load_config
    from ..transfer.annotations import load_annotations

    source = source_rig()
    saved = out / "clips" / f"{RETARGET_DEMO_CLIP}.npz"
    full = load_clip(saved) if time_scale == 1.0 and saved.is_file() else make_demo_clip(RETARGET_DEMO_CLIP, rig=source)
    clip = grasp_window(full, RETARGET_DEMO_FRAMES)
    clip_path = out / "retarget" / f"{RETARGET_DEMO_CLIP}_grasp.npz"
    clip.save(clip_path)
    print(f"clip {clip_path}: {clip.n_frames} frames of {RETARGET_DEMO_CLIP} around the first contact")
    config = load_config(None, "default")
    rows = ["| hand | DOFs | frames | seconds | median contact distance (mm) | failed frames | pictures |",
            "|---|---:|---:|---:|---:|---:|---|"]
    pictures = []
    pairs = pair_contacts(clip)  # the same clip for every hand: pair it once
    for name in hands:
        print(f"-- {name}")
        inputs = RunInputs.of(clip, source, demo_hand(name, resolution=resolution),
                              load_annotations(out / "annotations" / f"{name}.json"),
                              names={"clip": str(clip_path), "source_rig": clip.source_rig,
                                     "target_rig": f"demo:{name}@{resolution:g}"})
        result, paths = _run_retarget(inputs, config, Executor(workers=default_workers()), out / "retarget" / name,
                                  out / "rigs" / f"{name}.usda", pairs=pairs)
        s = result.summary
        links = ", ".join(f"[{label}]({name}/{file})" for label, file in
                          (("contact sheet", "contact_sheet.png"), ("preview", "preview.gif")) if file in paths)
        pictures.append((name, s, [file for file in ("contact_sheet.png", "preview.gif") if file in paths]))
        rows.append(f"| {name} | {s['dofs']} | {s['frames']} | {s['seconds']:.1f} | "
                    f"{_fmt_mm(s['contact_distance_median_mm'])} | {s['failed_frames']} | {links} |")
    table = "\n".join(rows) + "\n"
    title = f"Retarget of {clip_path.name} ({clip.n_frames} frames at {clip.fps:g} fps), preset default"
    (out / "retarget" / "summary.md").write_text(f"# {title}\n\n" + table)
    _write_demo_html(out / "retarget" / "index.html", title, pictures)
    print("\n" + table + f"wrote {out / 'retarget' / 'summary.md'}\nwrote {out / 'retarget' / 'index.html'} "
          "(every hand's contact sheet and preview)")


def _write_demo_html(path: Path, title: str, pictures) -> None:
    """index.html beside summary.md: per hand its figures, contact sheet and animated preview."""
    import html

    esc = html.escape
    parts = ["<!doctype html><html><head><meta charset='utf-8'>", f"<title>{esc(title)}</title>",
             "<style>body{font-family:sans-serif;margin:2em}img{margin:4px;vertical-align:top}</style></head><body>",
             f"<h1>{esc(title)}</h1>",
             "<p>Each hand: the contact sheet (captured source left, the delivered curve right, contacts coloured by "
             "their distance to the object) and the animated preview of the whole window.</p>"]
    for name, s, files in pictures:
        parts.append(f"<section><h2>{esc(name)}</h2><p>median contact distance "
                     f"{esc(_fmt_mm(s['contact_distance_median_mm']))} mm at the {esc(str(s['figures_at']))}; "
                     f"{s['failed_frames']} failed frames</p>")
        parts += [f"<img src='{esc(name)}/{esc(f)}' alt='{esc(name)} {esc(f)}'>" for f in files]
        parts.append("</section>")
    parts.append("</body></html>")
    path.write_text("\n".join(parts) + "\n", encoding="utf-8")
