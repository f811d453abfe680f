"""The ``handretarget`` command line. Heavy modules are imported inside each command so that
``--help`` is instant and ``bench`` can pin BLAS to one thread before numpy loads."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path



def _cmd_rig_demo(args) -> int:
    from .rig.demo_hands import DEMO_HANDS, demo_hand
    from .rig.io import save_rig

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    names = args.hand or list(DEMO_HANDS)
    rows = []
    for name in names:
        rig = demo_hand(name, resolution=args.resolution)
        path = out / f"{name}.usda"
        save_rig(rig, path)
        report = rig.surface.topology()
        rows.append((name, rig.n_dofs, rig.surface.n_vertices, len(rig.surface.faces), report.describe(), path))
    print(f"{'hand':<17} {'DOFs':>4} {'vertices':>9} {'faces':>7}  surface")
    for name, n_dofs, nv, nf, topo, path in rows:
        print(f"{name:<17} {n_dofs:>4} {nv:>9} {nf:>7}  {topo}  -> {path}")
    return 0


def _cmd_rig_info(args) -> int:
    from .rig.io import load_rig
    from .rig.summary import format_rig_info, rig_summary

    rig = load_rig(args.path, wrapper_resolution=args.wrapper_resolution, root_body=args.root_body)
    if args.json:
        print(json.dumps(rig_summary(rig), indent=2))
    else:
        print(format_rig_info(rig, source=str(args.path)))
    return 0


def _cmd_demo(args) -> int:
    """The README's main job: the demo hand library (USD), the demonstration clips, their
    dense contact pairing, a PNG strip of each clip, annotations from the source hand to every
    demo hand, the contact transfer onto each (report and pictures) and the retarget of one second
    of a clip onto every demo hand (USD animation, result and joint JSON, summary table)."""
    out = Path(args.out)
    print(f"== demo hand library -> {out / 'rigs'}")
    _cmd_rig_demo(argparse.Namespace(out=out / "rigs", hand=None, resolution=args.resolution))
    print(f"\n== demonstration clips -> {out / 'clips'}")
    _cmd_clip_demo(argparse.Namespace(out=out / "clips", clip=args.clip, time_scale=args.time_scale,
                                      resolution=0.004))
    clips = [c for c in sorted((out / "clips").glob("*.npz")) if not c.name.endswith(".pairs.npz")]
    print("\n== dense contact pairing")
    _cmd_clip_pair(argparse.Namespace(paths=clips, epsilon=0.015, per_frame=False, out=out / "clips"))
    print("\n== renders")
    for path in clips:
        _cmd_clip_render(argparse.Namespace(path=path, out=path.with_suffix(".png"), frames=None, count=6,
                                            view="three_quarter", size="320x320"))
    print(f"\n== annotations -> {out / 'annotations'}")
    _cmd_annotate_demo(argparse.Namespace(out=out / "annotations", resolution=args.resolution, source_resolution=0.004))
    print(f"\n== contact transfer onto every demo hand -> {out / 'transfer'}")
    from .clip import load_clip
    from .pairing import load_contact_pairs
    from .rig.demo_hands import DEMO_HANDS, demo_hand
    from .transfer.annotations import load_annotations

    jobs = [(c.stem, load_clip(c), load_contact_pairs(c.with_name(c.stem + ".pairs.npz"))) for c in clips]
    for name in DEMO_HANDS:
        print(f"-- {name}")
        _transfer_table(jobs, None, demo_hand(name, resolution=args.resolution),
                        load_annotations(out / "annotations" / f"{name}.json"), out / "transfer" / name, None)
    print(f"\n== retarget one second of {RETARGET_DEMO_CLIP} onto every demo hand -> {out / 'retarget'}")
    _retarget_demo(out, args.resolution, args.time_scale)
    return 0


#: The demo's retarget stage: one second (RETARGET_DEMO_FRAMES at 120 fps) of this clip at its
#: natural speed, from half a second before the first contact (reach, grasp, lift). A shortened
#: clip (time_scale < 1) would move faster than the acceleration threshold E_acc allows.
RETARGET_DEMO_CLIP = "bottle_pick_place"
RETARGET_DEMO_FRAMES = 120


def _retarget_demo(out: Path, resolution: float, time_scale: float) -> None:
    """Retarget a short window of the demo clip onto every demo hand with the proposed
    annotations (``out/annotations``) and the default preset; write ``out/retarget/<hand>/``
    and a summary table (``out/retarget/summary.md``)."""
    from .clip import load_clip
    from .clip.demo import grasp_window, make_demo_clip, source_rig
    from .execute import Executor, default_workers
    from .inputs import RunInputs
    from .pairing import pair_contacts
    from .rig.demo_hands import DEMO_HANDS, demo_hand
    from .solve.config import load_config
    from .transfer.annotations import load_annotations

    source = source_rig()
    saved = out / "clips" / f"{RETARGET_DEMO_CLIP}.npz"
    full = load_clip(saved) if time_scale == 1.0 and saved.is_file() else make_demo_clip(RETARGET_DEMO_CLIP, rig=source)
    clip = grasp_window(full, RETARGET_DEMO_FRAMES)
    clip_path = out / "retarget" / f"{RETARGET_DEMO_CLIP}_grasp.npz"
    clip.save(clip_path)
    print(f"clip {clip_path}: {clip.n_frames} frames of {RETARGET_DEMO_CLIP} around the first contact")
    config = load_config(None, "default")
    rows = ["| hand | DOFs | frames | seconds | median contact distance (mm) | failed frames |",
            "|---|---:|---:|---:|---:|---:|"]
    pairs = pair_contacts(clip)  # the same clip for every hand: pair it once
    for name in DEMO_HANDS:
        print(f"-- {name}")
        inputs = RunInputs.of(clip, source, demo_hand(name, resolution=resolution),
                              load_annotations(out / "annotations" / f"{name}.json"), clip=clip_path,
                              source_rig=clip.source_rig, target_rig=f"demo:{name}@{resolution:g}")
        result, _ = _run_retarget(inputs, config, Executor(workers=default_workers()), out / "retarget" / name,
                                  out / "rigs" / f"{name}.usda", pairs=pairs)
        s = result.summary
        rows.append(f"| {name} | {s['dofs']} | {s['frames']} | {s['seconds']:.1f} | "
                    f"{_fmt_mm(s['contact_distance_median_mm'])} | {s['failed_frames']} |")
    table = "\n".join(rows) + "\n"
    (out / "retarget" / "summary.md").write_text(
        f"# Retarget of {clip_path.name} ({clip.n_frames} frames at {clip.fps:g} fps), preset default\n\n" + table)
    print("\n" + table + f"wrote {out / 'retarget' / 'summary.md'}")


def _cmd_bench_kinematics(args) -> int:
    from .benchmarks.kinematics import run_kinematics_benchmark

    figures = run_kinematics_benchmark(hand=args.hand, n_points=args.points, repeats=args.repeats,
                                       resolution=args.resolution)
    if args.json:
        print(json.dumps(figures, indent=2))
        return 0
    print(f"kinematics benchmark: {figures['hand']} ({figures['dofs']} DOFs, {figures['joints']} joints, "
          f"{figures['surface_vertices']} surface vertices), {figures['points']} surface points, one thread")
    for key, label in (
        ("fk", "FK (joint transforms, DOF axes)"),
        ("fk_points_jacobians", "FK + points + point Jacobians"),
        ("fk_points_normals_jacobians", "FK + points, normals + both Jacobians"),
        ("fk_points_vjp", "FK + points vector-Jacobian product"),
        ("skin_all_vertices", "skin all surface vertices"),
    ):
        t = figures[key]
        print(f"  {label:<40} median {t['median_ms']:.3f} ms  (p10 {t['p10_ms']:.3f}, p90 {t['p90_ms']:.3f})")
    return 0


def _cmd_clip_demo(args) -> int:
    import numpy as np

    from .clip.demo import DEMO_CLIPS, make_demo_clip, source_rig

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
    from .clip import load_clip

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

    from .clip import load_clip
    from .render import render_clip_strip

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

    from .clip import load_clip
    from .clip.substitute import substitute_object

    clip = load_clip(args.clip)
    if args.object.startswith("demo:"):
        from .clip.objects import OBJECT_NAMES, make_object

        name = args.object[len("demo:"):]
        if name not in OBJECT_NAMES:
            raise _UsageError(f"unknown demo object {name!r} (known: {', '.join(OBJECT_NAMES)})")
        obj = make_object(name)
        vertices, faces = obj.vertices, obj.faces
    else:
        import trimesh

        from .errors import InputError

        try:
            mesh = trimesh.load(args.object, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many kinds for unreadable files
            raise InputError(f"not a readable mesh: {exc}", source=args.object) from None
        vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        name = Path(args.object).stem
    if args.scale:
        try:
            scale = [float(x) for x in args.scale.split(",")]
        except ValueError:
            raise _UsageError(f"--scale must be one or three numbers, got {args.scale!r}") from None
        if len(scale) not in (1, 3) or min(scale) <= 0:
            raise _UsageError(f"--scale must be one or three positive numbers, got {args.scale!r}")
        vertices = np.asarray(vertices, dtype=float) * np.array(scale if len(scale) == 3 else scale * 3)
    new, report = substitute_object(clip, vertices, faces, name=name, max_distance=args.max_distance)
    new.save(args.out)
    print(f"{args.clip}: object {clip.object_name} -> {new.object_name}; labelled vertices {report['labelled_vertices']}, "
          f"traced {report['traced']}, dropped {report['dropped']} (farther than {args.max_distance * 100:g} cm)")
    print(f"wrote {args.out}")
    return 0


def _cmd_clip_pair(args) -> int:
    import numpy as np

    from .clip import load_clip
    from .pairing import pair_contacts

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
    from .clip.grab import import_grab

    clip = import_grab(args.sequence, args.mano, object_mesh=args.object_mesh, table_mesh=args.table_mesh,
                       vtemp=args.vtemp, grab_root=args.grab_root)
    clip.save(args.out)
    counts = (clip.contact_labels > 0).sum(axis=1)
    print(f"wrote {args.out}: {clip.n_frames} frames at {clip.fps:g} fps, object {clip.object_name or '-'}, "
          f"{int((counts > 0).sum())} frames with right-hand contacts ({clip.source})")
    return 0


def _cmd_bench_pairing(args) -> int:
    if args.clip:
        import time

        from .clip import load_clip
        from .pairing import pair_contacts

        clip = load_clip(args.clip)
        start = time.perf_counter()
        pairs = pair_contacts(clip)
        seconds = time.perf_counter() - start
        s = pairs.summary()
        print(f"pairing benchmark on {args.clip}: {clip.n_frames} frames, {s['contacts']} contacts "
              f"({s['contacts'] / max(s['frames_with_contacts'], 1):.0f} per contact frame), {seconds:.2f} s, "
              f"{s['contacts'] / seconds:.0f} contacts/s; discarded {100 * s['discarded_fraction']:.1f}%, "
              f"median gap {s['gap_median_mm']:.2f} mm")
        return 0
    from .benchmarks.pairing import run_pairing_benchmark

    fig = run_pairing_benchmark(n_frames=args.frames, contacts_per_frame=args.contacts)
    print(f"pairing benchmark: {fig['frames']} frames x {fig['contacts_per_frame']} contacts "
          f"({fig['contacts']} total), hand {fig['hand_faces']} faces, one core: {fig['seconds']:.2f} s "
          f"({fig['ms_per_frame']:.2f} ms/frame, {fig['contacts_per_second']:.0f} contacts/s)")
    return 0


def _cmd_annotate_propose(args) -> int:
    from .rig.io import resolve_rig
    from .transfer.annotations import save_annotations
    from .transfer.propose import propose_annotations

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
    from .rig.demo_hands import DEMO_HANDS
    from .transfer.annotations import save_annotations
    from .transfer.propose import propose_annotations
    from .rig.demo_hands import demo_hand

    out = Path(args.out)
    source = demo_hand("source_human", resolution=args.source_resolution)
    for name in DEMO_HANDS:
        target = demo_hand(name, resolution=args.resolution)
        path = out / f"{name}.json"
        save_annotations(propose_annotations(source, target), path)
        print(f"wrote {path}")
    return 0


def _transfer_setup(args):
    from .clip import load_clip
    from .rig.io import resolve_rig
    from .transfer.annotations import load_annotations

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
    from .pairing import pair_contacts

    load_clip, resolve_rig, target, annotations = _transfer_setup(args)
    frames = [int(f) for f in args.frames.split(",")] if args.frames else None
    jobs = []
    for clip_path in args.clip:
        clip = load_clip(clip_path)
        jobs.append((Path(clip_path).stem, clip, pair_contacts(clip, frames=frames)))
    _transfer_table(jobs, resolve_rig(args.source_rig) if args.source_rig else None, target, annotations,
                    Path(args.out) if args.out else None, frames)
    return 0


def _transfer_table(jobs, source, target, annotations, out, frames) -> None:
    """Transfer each (name, clip, pairs) onto ``target``; print a row each; with ``out``, write
    the report (JSON) and a picture (PNG) per clip."""
    from .rig.io import resolve_rig
    from .transfer.clip_transfer import render_transfer, transfer_clip, transfer_report

    print(f"{'clip':<22} {'contacts':>9} {'transferred':>11} {'dropped':>9} {'spread':>8}  dropped by curve")
    for name, clip, pairs in jobs:
        src = source or resolve_rig(clip.source_rig)
        result = transfer_clip(pairs, src, target, annotations)
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
    from .clip import load_clip
    from .pairing import pair_contacts
    from .rig.demo_hands import DEMO_HANDS, demo_hand
    from .rig.io import resolve_rig
    from .transfer.clip_transfer import transfer_clip, transfer_report
    from .transfer.propose import propose_annotations

    clips = [c for c in sorted(Path(args.clips).glob("*.npz")) if not c.name.endswith(".pairs.npz")]
    if not clips:
        raise _usage(f"no clips (*.npz) in {args.clips}")
    loaded = [(c.stem, load_clip(c)) for c in clips]
    step = max(1, args.every)
    pairs = {name: pair_contacts(clip, frames=range(0, clip.n_frames, step)) for name, clip in loaded}
    sources = {}
    targets = args.target or list(DEMO_HANDS)
    for target_name in targets:
        target = demo_hand(target_name, resolution=args.resolution)
        print(f"\n== {target_name} ({target.surface.n_vertices} vertices)")
        print(f"{'clip':<22} {'contacts':>9} {'transferred':>11} {'dropped':>9} {'spread':>8}  dropped by curve")
        for name, clip in loaded:
            source = sources.setdefault(clip.source_rig, resolve_rig(clip.source_rig))
            annotations = propose_annotations(source, target)
            report = transfer_report(transfer_clip(pairs[name], source, target, annotations), source, target)
            _print_transfer_row(name, report)
    return 0


class _ProgressBar:
    """``progress(stage, done, total)`` printed on stderr: one line redrawn with \\r on a
    terminal, otherwise a line when a stage starts and at most every ``every`` seconds."""

    def __init__(self, stream=None, every: float = 10.0):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.every, self.stage, self.last = every, None, 0.0

    def __call__(self, stage: str, done: int, total: int) -> None:
        import time

        now = time.monotonic()
        new = stage != self.stage
        if self.tty:
            filled = int(24 * done / max(total, 1))
            self.stream.write(("\n" if new and self.stage else "\r")
                              + f"{stage:<16} [{'#' * filled}{'.' * (24 - filled)}] {done}/{total}".ljust(60))
        elif new or now - self.last >= self.every:
            self.stream.write(f"{stage}: {done}/{total}\n")
            self.last = now
        self.stage = stage
        self.stream.flush()

    def close(self) -> None:
        if self.tty and self.stage:
            self.stream.write("\n")
            self.stream.flush()


def _parse_sets(items) -> dict:
    """``["solver.maxeval=50", "fit.optimize_knots=true"]`` -> overrides; values are TOML values
    (numbers, booleans, quoted strings), anything else is taken as a string."""
    import tomllib

    out = {}
    for item in items or []:
        key, eq, text = item.partition("=")
        if not eq or not key.strip():
            raise _usage(f"--set expects KEY=VALUE, got {item!r}")
        try:
            value = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            value = text
        out[key.strip()] = value
    return out


def _run_retarget(inputs, config, executor, out, rig_path, pairs=None):
    """Retarget with a progress bar on stderr and write the result files; (result, paths)."""
    from .pipeline import retarget

    bar = _ProgressBar()
    executor.progress = bar
    try:
        result = retarget(inputs, config, executor, pairs=pairs)
    finally:
        bar.close()
    return result, result.write(out, rig_path)


def _fmt_mm(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def _executor(args):
    """The executor of the command's options (--workers, --dask-scheduler, --atlas-cache)."""
    from .execute import Executor, default_workers

    return Executor(workers=args.workers or default_workers(), dask_scheduler=getattr(args, "dask_scheduler", "") or "",
                    atlas_cache=getattr(args, "atlas_cache", None))


def _cmd_retarget(args) -> int:
    from .inputs import load_inputs
    from .solve.config import load_config

    config = load_config(args.config, args.preset, _parse_sets(args.set))
    inputs = load_inputs(args.clip, args.rig, args.annotations, source_rig=args.source_rig, frames=args.frames)
    rig_path = None if str(args.rig).startswith("demo:") else args.rig
    result, paths = _run_retarget(inputs, config, _executor(args), Path(args.out), rig_path)
    s = result.summary
    print(f"retargeted {args.clip} (frames {result.frames[0]}:{result.frames[1]}) onto {inputs.target_rig.name}: "
          f"{s['frames']} frames, {s['dofs']} DOFs, {s['control_points'] or 'no'} control points per DOF")
    print("  seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in result.timings.items()))
    print(f"  median contact distance {_fmt_mm(s['contact_distance_median_mm'])} mm over {s['contact_frames']} "
          f"contact frames; marker error {_fmt_mm(s['marker_error_median_mm'])} mm; failed frames "
          f"{s['failed_frames']}; unresolved entries {s['unresolved_entries']}; fit failures {s['fit_failures']}")
    for key, v in result.unused_settings.items():
        print(f"  note: {key} = {v['value']!r} is not used: {v['why']}")
    for path in paths.values():
        print(f"wrote {path}")
    return 0


def _cmd_evaluate(args) -> int:
    import json

    from .evaluate.report import write_evaluation

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
    from .evaluate.grid import run_grid

    paths = run_grid(args.out, targets=args.target, clips=args.clip, methods=args.method or None,
                     frames=args.frames, workers=args.workers, stride=args.stride)
    print(Path(paths["grid.md"]).read_text(encoding="utf-8"))
    for path in paths.values():
        print(f"wrote {path}")
    return 0


def _cmd_compare(args) -> int:
    from .evaluate.compare import run_compare

    paths = run_compare(args.clip, args.rig, Path(args.out), annotations=args.annotations, workers=args.workers,
                        stride=args.stride, frames=args.frames, overrides=_parse_sets(args.set))
    print(Path(paths["compare.md"]).read_text(encoding="utf-8"))
    for path in paths.values():
        print(f"wrote {path}")
    return 0


def _cmd_bench_transfer(args) -> int:
    from .benchmarks.transfer import run_transfer_benchmark

    fig = run_transfer_benchmark(n_frames=args.frames, contacts_per_frame=args.contacts, target=args.target,
                                 target_resolution=args.resolution)
    print(f"transfer benchmark: {fig['frames']} frames x {fig['contacts_per_frame']} contacts onto {fig['target']} "
          f"({fig['target_vertices']} vertices, {fig['landmarks']} landmarks), one thread")
    print(f"  per-landmark set-up (once per hand pair): {fig['setup_seconds']:.1f} s")
    print(f"  transfer of {fig['contacts']} contacts: {fig['transfer_seconds']:.2f} s "
          f"({fig['contacts_per_second']:.0f} contacts/s), {fig['dropped']} dropped")
    return 0


def _cmd_bench_retarget(args) -> int:
    from .benchmarks.retarget import run_retarget_benchmark

    fig = run_retarget_benchmark(n_frames=args.frames, target=args.target, workers=args.workers, preset=args.preset,
                                 speedup_frames=args.speedup_frames)
    if args.json:
        print(json.dumps(fig, indent=2, default=str))
        return 0
    s, t = fig["summary"], fig["timings"]
    print(f"retarget benchmark: {fig['frames']} frames of bottle_pick_place onto {fig['target']} "
          f"({fig['dofs']} DOFs, {fig['target_vertices']} vertices), preset {fig['preset']!r}, "
          f"{fig['workers']} workers")
    print(f"  (set-up, not timed: clip and hands built in {fig['setup_seconds']:.1f} s)")
    for stage, seconds in t.items():
        if stage != "total":
            print(f"  {stage:<12} {seconds:7.1f} s")
    print(f"  {'whole':<12} {t['total']:7.1f} s   (target: 60 s)")
    memory = f"{fig['peak_memory_bytes'] / 2**30:.2f} GiB" if fig["peak_memory_measured"] else "not measured (no /proc)"
    print(f"  peak memory (PSS, process and workers): {memory}   (target: 2 GiB)")
    g = fig["gradient"]
    print(f"  gradient speed-up on {len(g['frames'])} contact frames, MMA {g['analytic']['objective_evaluations']:.0f} "
          f"iterations (paper preset, no warm start): analytic {g['analytic']['ms_per_frame']:.0f} ms/frame, "
          f"forward differences {g['forward']['ms_per_frame']:.0f} ms/frame -> {g['speedup']:.1f}x   (target: 30x)")
    print(f"  result: median contact distance {s['contact_distance_median_mm']:.2f} mm over {s['contact_frames']} "
          f"contact frames, {s['failed_frames']} failed frames, {s['unresolved_entries']} unresolved DOF samples")
    return 0


class _UsageError(Exception):
    pass


def _usage(message: str) -> _UsageError:
    return _UsageError(message)


def _bench_retarget_arguments(p) -> None:
    p.add_argument("--frames", type=int, default=1000, help="clip length (the demo clip is stretched to it)")
    p.add_argument("--target", default="human_alt", help="demo hand (default: a 54-DOF human)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--preset", default="default")
    p.add_argument("--speedup-frames", type=int, default=4, help="frames timed with both gradient modes")
    p.add_argument("--json", action="store_true")


def _executor_arguments(p) -> None:
    """How a run executes (never what it computes)."""
    p.add_argument("--workers", type=int, help="worker processes for the frame solves (default: the CPU count)")
    p.add_argument("--dask-scheduler", default="", metavar="tcp://HOST:PORT",
                   help="solve the frames on this Dask cluster instead")
    p.add_argument("--atlas-cache", metavar="DIR", help="keep built contact-transfer atlases in this folder")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="handretarget", description="Contact-aware hand motion retargeting.")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the main demo job")
    demo.add_argument("--out", default="demo_out", help="output folder")
    demo.add_argument("--resolution", type=float, default=0.003, help="demo hands' mesh cell size in metres")
    demo.add_argument("--clip", action="append", help="only this demo clip (repeatable)")
    demo.add_argument("--time-scale", type=float, default=1.0, help="shorten (<1) the demo clips")
    demo.set_defaults(func=_cmd_demo)

    rig = sub.add_parser("rig", help="hand rigs")
    rig_sub = rig.add_subparsers(dest="rig_command", required=True)
    rig_demo = rig_sub.add_parser("demo", help="write the demo hand library as USD files")
    rig_demo.add_argument("--out", required=True, help="output folder")
    rig_demo.add_argument("--hand", action="append", help="only this demo hand (repeatable)")
    rig_demo.add_argument("--resolution", type=float, default=0.002, help="mesh cell size in metres")
    rig_demo.set_defaults(func=_cmd_rig_demo)
    rig_info = rig_sub.add_parser("info", help="describe a rig file (USD, URDF or MJCF)")
    rig_info.add_argument("path")
    rig_info.add_argument("--json", action="store_true", help="print JSON instead of text")
    rig_info.add_argument("--root-body", default=None, help="MJCF: the hand's root body")
    rig_info.add_argument("--wrapper-resolution", type=float, default=0.002,
                          help="URDF/MJCF: wrapper surface cell size in metres")
    rig_info.set_defaults(func=_cmd_rig_info)


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
    grab.add_argument("--mano", required=True, help="the MANO right-hand model (MANO_RIGHT.pkl)")
    grab.add_argument("--out", required=True, help="clip .npz to write")
    grab.add_argument("--object-mesh", help="the object's mesh (default: found under --grab-root)")
    grab.add_argument("--table-mesh", help="the table's mesh (default: found under --grab-root)")
    grab.add_argument("--vtemp", help="the subject's right-hand template mesh (778 vertices)")
    grab.add_argument("--grab-root", help="GRAB's root folder, to resolve the paths stored in the sequence")
    grab.set_defaults(func=_cmd_import_grab)

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

    transfer = sub.add_parser("transfer", help="carry a clip's contacts onto a target hand (report, PNG)")
    transfer.add_argument("--clip", action="append", required=True, help="clip .npz (repeatable)")
    transfer.add_argument("--rig", required=True, help="target rig: a file or demo:NAME[@RESOLUTION]")
    transfer.add_argument("--annotations", required=True, help="annotation JSON")
    transfer.add_argument("--source-rig", help="source rig (default: the one the clip records)")
    transfer.add_argument("--frames", help="comma-separated frames (default: all; the PNG shows 4)")
    transfer.add_argument("--out", help="folder for the report (.json) and the picture (.png)")
    transfer.set_defaults(func=_cmd_transfer)
    t_demo = sub.add_parser("transfer-demo", help="every demo clip onto every demo hand: shares and spread")
    t_demo.add_argument("--clips", required=True, help="folder of demo clips")
    t_demo.add_argument("--target", action="append", help="only this demo hand (repeatable)")
    t_demo.add_argument("--resolution", type=float, default=0.004, help="target hands' mesh cell size (m)")
    t_demo.add_argument("--every", type=int, default=5, help="use every N-th frame")
    t_demo.set_defaults(func=_cmd_transfer_demo)

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
    _executor_arguments(ret)
    ret.set_defaults(func=_cmd_retarget)

    ev = sub.add_parser("evaluate", help="metrics and plots of a retarget output folder (metrics.json, PNGs)")
    ev.add_argument("dir", help="a folder written by handretarget retarget")
    ev.add_argument("--stride", type=int, default=1, help="measure intersections every N-th frame (default 1)")
    ev.add_argument("--self-stride", type=int, help="self intersection every N-th frame (default: --stride)")
    ev.add_argument("--no-render", action="store_true", help="skip frames.png")
    ev.set_defaults(func=_cmd_evaluate)

    grid = sub.add_parser("grid", help="every demo target x demo clip with our method and both baselines: "
                                       "table (md, csv) and HTML report; reruns reuse finished cells")
    grid.add_argument("--out", required=True, help="output folder")
    grid.add_argument("--target", action="append", help="only this demo hand (repeatable)")
    grid.add_argument("--clip", action="append", help="only this demo clip (repeatable)")
    grid.add_argument("--method", action="append", choices=["contacts", "fingertips", "keyvectors"],
                      help="only this method (repeatable)")
    grid.add_argument("--frames", type=int, default=120, help="frames per clip window (default 120)")
    grid.add_argument("--stride", type=int, default=4, help="intersections every N-th frame (default 4)")
    grid.add_argument("--workers", type=int, help="worker processes per retarget")
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

    bench = sub.add_parser("bench", help="print performance figures (without a sub-command: the whole retarget)")
    _bench_retarget_arguments(bench)
    bench.set_defaults(func=_cmd_bench_retarget)
    bench_sub = bench.add_subparsers(dest="bench_command")
    whole = bench_sub.add_parser("retarget", help="the whole pipeline on a 1000-frame clip (the default)")
    _bench_retarget_arguments(whole)
    whole.set_defaults(func=_cmd_bench_retarget)
    kin = bench_sub.add_parser("kinematics", help="FK + Jacobians of many surface points")
    kin.add_argument("--hand", default="source_human")
    kin.add_argument("--points", type=int, default=500)
    kin.add_argument("--repeats", type=int, default=2000)
    kin.add_argument("--resolution", type=float, default=0.002)
    kin.add_argument("--json", action="store_true")
    kin.set_defaults(func=_cmd_bench_kinematics)
    pair = bench_sub.add_parser("pairing", help="dense contact pairing over many frames")
    pair.add_argument("--frames", type=int, default=1000)
    pair.add_argument("--contacts", type=int, default=300, help="contacts per frame")
    pair.add_argument("--clip", help="time a clip file instead of the synthetic one")
    pair.set_defaults(func=_cmd_bench_pairing)
    xfer = bench_sub.add_parser("transfer", help="contact transfer onto a ~10k-vertex target")
    xfer.add_argument("--frames", type=int, default=1000)
    xfer.add_argument("--contacts", type=int, default=300, help="contacts per frame")
    xfer.add_argument("--target", default="human_alt", help="demo hand")
    xfer.add_argument("--resolution", type=float, default=0.0025, help="target mesh cell size (m)")
    xfer.set_defaults(func=_cmd_bench_transfer)

    # The job service lives in server/ (thin around this core); its commands are registered
    # here so there is one `handretarget` entry point.
    try:
        from server.cli import add_commands
    except ImportError:  # the core installed without the service
        pass
    else:
        add_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "bench":
        # Figures are per core: pin BLAS before numpy is first imported.
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(var, "1")
    from .errors import InputError

    try:
        return args.func(args)
    except (InputError, _UsageError) as err:
        print(f"handretarget: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
