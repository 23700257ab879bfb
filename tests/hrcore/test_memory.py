"""hrcore.memory: freed heap pages go back to the system."""

import sys

import numpy as np
import pytest

from hrcore.memory import release_free_memory


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024.0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc_trim and /proc are Linux's")
def test_release_free_memory_returns_freed_heap():
    big = np.ones(1_000_000)
    del big  # freeing an 8 MB mapping raises glibc's mmap threshold above 0.8 MB
    release_free_memory()
    before = _rss_mb()
    # so these arrays live in the heap, not in mappings of their own
    chunks = [np.ones(100_000) for _ in range(600)]  # 600 x 0.8 MB = 480 MB
    del chunks[:-1]  # the last one stays: the freed ones lie below it, where a heap cannot shrink by itself
    held = _rss_mb()
    assert release_free_memory() is True
    assert _rss_mb() < held - 300  # at least 300 of the 480 MB given back
    assert _rss_mb() < before + 100


def test_no_explicit_trim_where_glibc_is_told_when_to_trim(monkeypatch):
    import hrcore.memory as memory

    calls = []
    monkeypatch.setattr(memory, "_malloc_trim", lambda: lambda pad: calls.append(pad) or 1)
    monkeypatch.setattr(memory, "_glibc_trims_by_itself", lambda: True)  # a Dask worker's start
    assert memory.release_free_memory() is False and calls == []
    monkeypatch.setattr(memory, "_glibc_trims_by_itself", lambda: False)
    assert memory.release_free_memory() is True and calls == [0]


def test_the_start_environment_decides_not_the_current_one(monkeypatch):
    import subprocess

    import hrcore.memory as memory

    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "65536")  # set now, after this process started
    memory._glibc_trims_by_itself.cache_clear()
    assert memory._glibc_trims_by_itself() is False
    code = "import hrcore.memory as m; print(m._glibc_trims_by_itself())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "True"  # a process started with it


@pytest.mark.parametrize("version", ["v2", "v1"])
def test_the_cgroups_tightest_room_counts_its_droppable_cache(tmp_path, monkeypatch, version):
    """A container's limit, from the process's own cgroup up (the parent's tighter here), less what it holds but
    its inactive file cache (a review: the file cache that grew to the limit read as no room; only the root's
    v2 files were read)."""
    import hrcore.memory as memory

    root = tmp_path / "cgroup"
    own = root / "slice" / "job"
    own.mkdir(parents=True)
    limit, usage, cache = ("memory.max", "memory.current", "inactive_file") if version == "v2" else (
        "memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")
    for folder, bytes_limit, used, dropped in ((own, 8 << 30, 6 << 30, 3 << 30), (root / "slice", 4 << 30, 3 << 30, 1 << 30)):
        (folder / limit).write_text(f"{bytes_limit}\n")
        (folder / usage).write_text(f"{used}\n")
        (folder / "memory.stat").write_text(f"anon 123\n{cache} {dropped}\n")
    (root / limit).write_text("max\n" if version == "v2" else "9223372036854771712\n")
    proc = tmp_path / "cgroup.txt"
    proc.write_text("0::/slice/job\n" if version == "v2" else "4:memory:/slice/job\n3:cpu:/\n")
    monkeypatch.setattr(memory, "_PROC_CGROUP", str(proc))
    files = dict(memory._CGROUP_FILES)
    files[version] = (str(root), *files[version][1:])
    monkeypatch.setattr(memory, "_CGROUP_FILES", files)
    assert memory._cgroup_room() == (4 << 30) - (3 << 30) + (1 << 30)  # the parent's: 2 GB, not the job's 5
    proc.write_text("0::/\n" if version == "v2" else "4:memory:/\n")
    assert memory._cgroup_room() is None  # the root's limit is none
