"""What several commands share: the usage error, --set overrides, the executor options, the progress bar
and the retarget-and-write step."""

from __future__ import annotations

import sys


class _UsageError(Exception):
    pass


def _usage(message: str) -> _UsageError:
    return _UsageError(message)


def _executor_arguments(p) -> None:
    """How a run executes (never what it computes)."""
    p.add_argument("--workers", type=int, help="worker processes for the frame solves (default: the CPU count)")
    p.add_argument("--dask-scheduler", default="", metavar="tcp://HOST:PORT",
                   help="solve the frames on this Dask cluster instead")
    p.add_argument("--atlas-cache", metavar="DIR", help="keep built contact-transfer atlases in this folder")


def _executor(args):
    """The executor of the command's options (--workers, --dask-scheduler, --atlas-cache)."""
    from ..execute import Executor, default_workers

    return Executor(workers=default_workers() if args.workers is None else args.workers, dask_scheduler=getattr(args, "dask_scheduler", "") or "",
                    atlas_cache=getattr(args, "atlas_cache", None))


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


def _run_retarget(inputs, config, executor, out, rig_path, pairs=None, control_rate_hz=None, pictures=True):
    """Retarget with a progress bar on stderr and write the result files (a robot's joint
    commands at ``control_rate_hz``; the contact sheet and preview unless ``pictures`` is false);
    (result, paths)."""
    import numpy as np

    from ..errors import InputError
    from ..export.robot_trajectory import is_robot
    from ..pipeline import retarget

    if control_rate_hz is not None and not is_robot(inputs.target_rig):
        raise InputError(f"--rate resamples a robot's joint commands; {inputs.target_rig.name!r} is not a URDF or "
                         "MJCF robot (its curves are in animation.usda)", element="rate")
    if control_rate_hz is not None and not (np.isfinite(control_rate_hz) and control_rate_hz > 0):
        raise InputError(f"--rate must be a positive number of Hz, got {control_rate_hz}", element="rate")

    bar = _ProgressBar()
    executor.progress = bar
    try:
        result = retarget(inputs, config, executor, pairs=pairs)
    finally:
        bar.close()
    return result, result.write(out, rig_path, control_rate_hz=control_rate_hz, pictures=pictures)


def _fmt_mm(value) -> str:
    return "-" if value is None else f"{value:.2f}"
