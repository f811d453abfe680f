"""``handretarget bench [retarget|kinematics|pairing|transfer]``: performance figures. ``main``
pins BLAS to one thread before numpy loads when the command is ``bench``."""

from __future__ import annotations

import argparse
import json


def _non_negative(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def add_commands(sub) -> None:
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
    keys = bench_sub.add_parser("keypoints", help="retarget-keypoints onto a robot hand (ms per frame, root included)")
    keys.add_argument("--rig", default="installed:leap", help="rig (default: the LEAP hand)")
    keys.add_argument("--frames", type=int, default=1000)
    keys.add_argument("--json", action="store_true")
    keys.set_defaults(func=_cmd_bench_keypoints)


#: The stages that solve frames (what the collision terms make dearer).
SOLVE_STAGES = ("root pass", "full pass", "coherence", "filter", "refinement", "curve polish")


def _bench_retarget_arguments(p) -> None:
    p.add_argument("--frames", type=int, default=1000, help="clip length (the demo clip is stretched to it)")
    p.add_argument("--target", default="human_alt", help="demo hand (default: a 54-DOF human)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--preset", default="default")
    p.add_argument("--speedup-frames", type=_non_negative, default=4,
                   help="frames timed with both gradient modes (0: skip the speed-up)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--collision", action="store_true",
                   help="the collision terms on (lambda_p = lambda_sc = 10), then the same run without them")
    p.add_argument("--no-collision-off", dest="collision_off", action="store_false",
                   help="skip the second run without the collision terms")


def _cmd_bench_retarget(args) -> int:
    from ..benchmarks.retarget import run_retarget_benchmark

    fig = run_retarget_benchmark(n_frames=args.frames, target=args.target, workers=args.workers, preset=args.preset,
                                 speedup_frames=args.speedup_frames, collision_off=args.collision_off,
                                 collision=args.collision)
    if args.json:
        print(json.dumps(fig, indent=2, default=str))
        return 0
    s, t = fig["summary"], fig["timings"]
    print(f"retarget benchmark: {fig['frames']} frames of bottle_pick_place onto {fig['target']} "
          f"({fig['dofs']} DOFs, {fig['target_vertices']} vertices), preset {fig['preset']!r}, "
          f"{fig['workers']} workers")
    print(f"  (set-up, not timed: clip and hands built in {fig['setup_seconds']:.1f} s)")
    scratch = fig["scratch"]["timings"]
    print(f"  {'stage':<12} {'cached':>8} {'scratch':>8}   (scratch: atlas and grids built, as on a new hand pair)")
    for stage, seconds in t.items():
        if stage != "total":
            print(f"  {stage:<12} {seconds:7.1f} s {scratch.get(stage, float('nan')):7.1f} s")
    duration = fig["duration_seconds"]
    print(f"  {'whole':<12} {t['total']:7.1f} s {scratch['total']:7.1f} s   (targets: 8.3 s cached, 15 s from scratch)")
    print(f"  real-time factor (the clip's {duration:.2f} s over the wall time): {duration / t['total']:.3f} cached, "
          f"{duration / scratch['total']:.3f} from scratch   (target: >= 1.0 cached)")
    memory = f"{fig['peak_memory_bytes'] / 2**30:.2f} GiB" if fig["peak_memory_measured"] else "not measured (no /proc)"
    print(f"  peak memory (PSS, process and workers): {memory}   (target: 1.5 GiB)")
    g = fig["gradient"]
    if g is None:
        print("  gradient speed-up: not measured (--speedup-frames 0)")
    else:
        print(f"  gradient speed-up on {len(g['frames'])} contact frames, MMA {g['analytic']['objective_evaluations']:.0f} "
              f"iterations (paper preset, no warm start): analytic {g['analytic']['ms_per_frame']:.0f} ms/frame, "
              f"forward differences {g['forward']['ms_per_frame']:.0f} ms/frame -> {g['speedup']:.1f}x   (target: 30x)")
    print(f"  result: median contact distance {s['contact_distance_median_mm']:.2f} mm at the delivered curve "
          f"({s['solved_contact_distance_median_mm']:.2f} mm at the solved frames; {s['control_points']} control "
          f"points over {fig['frames']} frames at {fig['fps']:g} fps) over {s['contact_frames']} contact frames, "
          f"{s['failed_frames']} failed frames, {s['unresolved_entries']} unresolved DOF samples")
    off = fig.get("collision_off")
    if off:
        # the second run finds the atlas in memory: the solving stages compare, not the whole
        on_s, off_s = (sum(v for k, v in timings.items() if k in SOLVE_STAGES) for timings in (t, off["timings"]))
        print(f"  without the collision terms (lambda_p = lambda_sc = 0): whole {off['timings']['total']:.1f} s "
              f"(atlas cached), median contact distance {off['summary']['contact_distance_median_mm']:.2f} mm "
              f"({off['summary']['solved_contact_distance_median_mm']:.2f} mm at the solved frames)")
        print(f"  solving stages ({', '.join(SOLVE_STAGES)}): {on_s:.1f} s with the collision terms, {off_s:.1f} s "
              f"without -> {on_s / off_s:.2f}x   (target: at most 1.5x)")
    return 0


def _cmd_bench_keypoints(args) -> int:
    from ..benchmarks.keypoints import run_keypoints_benchmark

    fig = run_keypoints_benchmark(args.rig, n_frames=args.frames)
    if args.json:
        print(json.dumps(fig, indent=2))
        return 0
    print(f"keypoints benchmark: {fig['frames']} frames at {fig['fps']:g} fps of {len(fig['keypoints'])} keypoints "
          f"onto {fig['rig']} ({fig['dofs']} DOFs), one process")
    print(f"  {fig['ms_per_frame']:.2f} ms per frame (whole wall time over frames, root included; target: 2 ms), "
          f"{fig['evaluations_per_frame']:.1f} evaluations per frame, {fig['frames_retried']} frames solved again "
          f"from the rest fingers")
    print(f"  keypoint error at the solved frames (the poses that made them: 0): median {fig['error_median_mm']:.4f} mm, "
          f"max {fig['error_max_mm']:.4f} mm")
    return 0


def _cmd_bench_kinematics(args) -> int:
    from ..benchmarks.kinematics import run_kinematics_benchmark

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


def _cmd_bench_pairing(args) -> int:
    if args.clip:
        import time

        from ..clip import load_clip
        from ..pairing import pair_contacts

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
    from ..benchmarks.pairing import run_pairing_benchmark

    fig = run_pairing_benchmark(n_frames=args.frames, contacts_per_frame=args.contacts)
    print(f"pairing benchmark: {fig['frames']} frames x {fig['contacts_per_frame']} contacts "
          f"({fig['contacts']} total), hand {fig['hand_faces']} faces, one core: {fig['seconds']:.2f} s "
          f"({fig['ms_per_frame']:.2f} ms/frame, {fig['contacts_per_second']:.0f} contacts/s)")
    return 0


def _cmd_bench_transfer(args) -> int:
    from ..benchmarks.transfer import run_transfer_benchmark

    fig = run_transfer_benchmark(n_frames=args.frames, contacts_per_frame=args.contacts, target=args.target,
                                 target_resolution=args.resolution)
    print(f"transfer benchmark: {fig['frames']} frames x {fig['contacts_per_frame']} contacts onto {fig['target']} "
          f"({fig['target_vertices']} vertices, {fig['landmarks']} landmarks), one thread")
    print(f"  per-landmark set-up (once per hand pair): {fig['setup_seconds']:.1f} s")
    print(f"  transfer of {fig['contacts']} contacts: {fig['transfer_seconds']:.2f} s "
          f"({fig['contacts_per_second']:.0f} contacts/s), {fig['dropped']} dropped")
    return 0
