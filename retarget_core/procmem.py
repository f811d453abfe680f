"""Memory of a process and its descendants, read from Linux /proc: what the benchmark's peak
memory, the service's upload validation limit and its job memory limit all measure. An
address-space rlimit would break embree and OpenBLAS, so limits sample these instead."""

from __future__ import annotations

import os


def process_memory_bytes(pid: int) -> int:
    """Proportional set size of a process (bytes): pages shared with forked workers are
    counted once across them, unlike RSS. 0 when the process is gone."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as fh:
            for line in fh:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def descendants(root: int) -> list[int]:
    """Pids of every descendant of ``root`` (Linux /proc), children before grandchildren."""
    children: dict[int, list[int]] = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(entry.name))
    out, stack = [], list(children.get(root, []))
    while stack:
        pid = stack.pop()
        out.append(pid)
        stack += children.get(pid, [])
    return out


def peak_rss_bytes(pid: int | str = "self") -> int:
    """The peak resident set size (``VmHWM``) of a process since it started (its exec), bytes."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def tree_memory_bytes(root: int) -> int:
    """PSS (bytes) of ``root`` and all its descendants."""
    return sum(process_memory_bytes(pid) for pid in [root, *descendants(root)])
