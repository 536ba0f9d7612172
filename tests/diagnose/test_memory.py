"""The memory left for diagnosis workers, read from fake /proc and cgroup trees (v1 and v2) built here."""

from __future__ import annotations

from pathlib import Path

import pytest

from magcal_cli.diagnose import memory

MIB = 2**20


def _proc(root: Path, cgroup: str, rss_anon_mib: int = 300, available_mib: int = 20_000) -> Path:
    """A /proc with this process's anonymous memory, its cgroup line(s) and the kernel's MemAvailable."""
    (root / "self").mkdir(parents=True)
    (root / "self" / "status").write_text(f"Name:\tpython\nRssAnon:\t  {rss_anon_mib * 1024} kB\nRssFile:\t 9 kB\n")
    (root / "self" / "cgroup").write_text(cgroup)
    (root / "meminfo").write_text(f"MemTotal: 99 kB\nMemAvailable:   {available_mib * 1024} kB\n")
    return root


def _v1(sysfs: Path, path: str, limit: int, rss: int) -> None:
    """A cgroup v1 memory group with its hierarchical limit and anonymous use (bytes)."""
    group = sysfs / "memory" / path
    group.mkdir(parents=True)
    (group / "memory.stat").write_text(f"cache 5\nrss 1\nhierarchical_memory_limit {limit}\ntotal_cache 700000000\n"
                                       f"total_rss {rss}\n")


def test_v1_limit_less_anonymous_use_and_page_cache_left_out(tmp_path: Path) -> None:
    """A 1 GiB v1 group with 550 MiB anonymous (and 700 MB of page cache, reclaimable): 474 MiB left, so a process
    holding 550 MiB of its own gets no worker, one holding 200 MiB two of three."""
    _v1(tmp_path / "sys", "box", 1024 * MIB, 550 * MIB)
    proc = _proc(tmp_path / "proc", "4:memory:/box\n0::/\n", rss_anon_mib=550)
    assert memory.available(proc, tmp_path / "sys") == 474 * MIB
    assert memory.workers(1, proc, tmp_path / "sys") == 0
    (proc / "self" / "status").write_text("RssAnon:\t204800 kB\n")
    assert memory.workers(3, proc, tmp_path / "sys") == 2          # (474 - 64) // 200


def test_v2_the_tightest_level_above_counts(tmp_path: Path) -> None:
    """v2: a 2 GiB limit on the parent group and none ("max") on the process's own: the parent's counts."""
    sysfs = tmp_path / "sys"
    own = sysfs / "user.slice" / "job"
    own.mkdir(parents=True)
    (sysfs / "user.slice" / "memory.max").write_text(f"{2048 * MIB}\n")
    (sysfs / "user.slice" / "memory.stat").write_text(f"anon {1000 * MIB}\nfile 900000000\n")
    (own / "memory.max").write_text("max\n")
    (own / "memory.stat").write_text(f"anon {900 * MIB}\n")
    proc = _proc(tmp_path / "proc", "0::/user.slice/job\n")
    assert memory.available(proc, sysfs) == 1048 * MIB
    assert memory.workers(8, proc, sysfs) == 3                        # (1048 - 64) // 300


@pytest.mark.parametrize("available_mib", [100, 20_000])
def test_no_cgroup_limit_the_kernels_available_memory(tmp_path: Path, available_mib: int) -> None:
    """No limit anywhere (v1's "unlimited" near 2^63): the kernel's MemAvailable alone decides."""
    _v1(tmp_path / "sys", "", 2**63 - 4096, 10 * MIB)
    proc = _proc(tmp_path / "proc", "4:memory:/\n", rss_anon_mib=300, available_mib=available_mib)
    assert memory.available(proc, tmp_path / "sys") == available_mib * MIB
    assert memory.workers(1, proc, tmp_path / "sys") == (0 if available_mib == 100 else 1)


def test_nothing_readable_no_limit(tmp_path: Path) -> None:
    """No /proc (another system): the workers asked for, not none."""
    assert memory.available(tmp_path, tmp_path) is None
    assert memory.workers(2, tmp_path, tmp_path) == 2
