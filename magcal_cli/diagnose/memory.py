"""How many more diagnosis workers the memory left allows (Linux; elsewhere no limit is known).

A forked worker fits as its parent does, so it needs about what the parent holds of its own (its anonymous
resident memory): measured on a two-hour log, a fold worker's private memory was 0.7 of its parent's (issue 39).
The memory left is the least of the kernel's MemAvailable and, for every cgroup above this process with a limit,
that limit less the anonymous memory charged to it (the log's page cache is reclaimable and does not count). A
machine or container with too little left runs the items in turn instead of being killed out of memory.
"""

from __future__ import annotations

from pathlib import Path

#: the memory kept free beside the workers (bytes): the caller's own transient peaks
MARGIN = 64 * 2**20
#: cgroup v1 reports "no limit" as a number near 2**63
NO_LIMIT = 2**60


def workers(wanted: int, proc: Path = Path("/proc"), sysfs: Path = Path("/sys/fs/cgroup")) -> int:
    """Of `wanted` more workers, how many the memory left allows (`wanted` where it cannot be told)."""
    need = _kib(proc / "self" / "status", "RssAnon:")
    left = available(proc, sysfs)
    if wanted <= 0 or need is None or left is None:
        return max(wanted, 0)
    return max(0, min(wanted, int((left - MARGIN) // max(need, 1))))


def available(proc: Path = Path("/proc"), sysfs: Path = Path("/sys/fs/cgroup")) -> int | None:
    """Bytes this process tree can still use (None: nothing known)."""
    found = [v for v in (_kib(proc / "meminfo", "MemAvailable:"), *_cgroup_left(proc, sysfs)) if v is not None]
    return min(found) if found else None


def _kib(path: Path, key: str) -> int | None:
    """The value in bytes of a "key N kB" line of a /proc file (None: absent or unreadable)."""
    try:
        for line in path.read_text().splitlines():
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _stat(path: Path, key: str) -> int | None:
    """The value of a "key N" line of a cgroup's memory.stat (None: absent or unreadable)."""
    try:
        for line in path.read_text().splitlines():
            name, _, value = line.partition(" ")
            if name == key:
                return int(value)
    except (OSError, ValueError):
        return None
    return None


def _limit(path: Path) -> int | None:
    """A cgroup limit file's bytes (None: "max", no limit, or unreadable)."""
    try:
        text = path.read_text().strip()
        value = None if text == "max" else int(text)
    except (OSError, ValueError):
        return None
    return value if value is not None and value < NO_LIMIT else None


def _cgroup_left(proc: Path, sysfs: Path) -> list[int | None]:
    """Limit less anonymous use of this process's memory cgroup and, in v2, of each cgroup above it."""
    try:
        lines = (proc / "self" / "cgroup").read_text().splitlines()
    except OSError:
        return []
    out: list[int | None] = []
    for line in lines:
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if "memory" in controllers.split(","):              # v1: the hierarchy's own totals
            group = sysfs / "memory" / path.lstrip("/")
            limit = _stat(group / "memory.stat", "hierarchical_memory_limit")
            used = _stat(group / "memory.stat", "total_rss")
            if limit is not None and limit < NO_LIMIT and used is not None:
                out.append(limit - used)
        elif controllers == "":                               # v2: every level may set memory.max
            group = sysfs / path.lstrip("/")
            for level in (group, *group.parents):
                if level == sysfs.parent:
                    break
                limit, used = _limit(level / "memory.max"), _stat(level / "memory.stat", "anon")
                if limit is not None and used is not None:
                    out.append(limit - used)
    return out
