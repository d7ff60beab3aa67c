"""The CLI's process environment: OpenMP threads wait passively unless the user says otherwise; glibc serves every
thread from one arena (but for `train`), unless switched off."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from hgca_core import hardware

PROBE = ("import os, sys; from hgca_core import cli; sys.argv = ['hgca', '--version']\n"
         "try:\n    cli.main()\nexcept SystemExit:\n    pass\nprint(os.environ.get('OMP_WAIT_POLICY'))")


@pytest.mark.parametrize("given, want", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_omp_wait_policy_defaults_to_passive(given: str | None, want: str) -> None:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given:
        env["OMP_WAIT_POLICY"] = given
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.strip().splitlines()[-1] == want, out.stderr


# After the CLI's set-up, four threads allocate a block each; print how many arenas (heaps) glibc then holds.
ARENA_PROBE = """
import ctypes, os, sys, tempfile, threading
import numpy as np
from hgca_core import cli
try:
    cli.main(sys.argv[1:])
except SystemExit:
    pass
keep = []
threads = [threading.Thread(target=lambda: keep.append(np.ones(1 << 17))) for _ in range(4)]
for t in threads:
    t.start()
for t in threads:
    t.join()
libc = ctypes.CDLL("libc.so.6")
libc.fdopen.restype, libc.fdopen.argtypes = ctypes.c_void_p, [ctypes.c_int, ctypes.c_char_p]
libc.malloc_info.argtypes, libc.fclose.argtypes = [ctypes.c_int, ctypes.c_void_p], [ctypes.c_void_p]
with tempfile.TemporaryFile() as f:
    fp = libc.fdopen(os.dup(f.fileno()), b"w")
    libc.malloc_info(0, fp)
    libc.fclose(fp)
    f.seek(0)
    print(f.read().decode().count("<heap nr="))
"""

glibc_only = pytest.mark.skipif(hardware.glibc() is None, reason="the allocator tuning is glibc's")


def _arenas(*argv: str, **extra: str) -> int:
    """glibc's heaps after `hgca ARGV` (default `--version`) set the probe process up."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "HGCA_ALLOCATOR"}
    env.update(extra)
    out = subprocess.run([sys.executable, "-c", ARENA_PROBE, *(argv or ("--version",))], env=env, capture_output=True,
                         text=True, timeout=60)
    assert out.stdout.strip(), out.stderr
    return int(out.stdout.strip().splitlines()[-1])


@glibc_only
def test_cli_serves_every_thread_from_one_arena() -> None:
    """glibc's defaults give new threads arenas of their own; after the CLI's set-up they share one. A user's own
    MALLOC_* setting, or HGCA_ALLOCATOR=system, is left alone."""
    assert _arenas() == 1
    assert _arenas(HGCA_ALLOCATOR="system") > 1
    assert _arenas(MALLOC_TRIM_THRESHOLD_="1000000") > 1


@glibc_only
def test_train_keeps_glibcs_arenas() -> None:
    """`hgca train` keeps glibc's arenas (its recipes' step times were taken with them)."""
    assert _arenas("train", "coarse", "--help") > 1


def test_tune_allocator_respects_the_switch(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HGCA_ALLOCATOR", "system")
    assert hardware.tune_allocator() is False
    monkeypatch.delenv("HGCA_ALLOCATOR")
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "1000")
    assert hardware.tune_allocator() is False


# Fill 64 MiB of the heap with 64 KiB blocks (below glibc's mmap threshold), free all but the last (which pins the
# heap's top), and print the resident MiB before and after `release_free_memory`.
TRIM_PROBE = """
import ctypes
from hgca_core.hardware import release_free_memory
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
blocks = [libc.malloc(64 << 10) for _ in range(1024)]
for b in blocks:
    ctypes.memset(b, 1, 64 << 10)
for b in blocks[:-1]:
    libc.free(b)
before = rss()
release_free_memory()
print(before, rss())
"""


@glibc_only
def test_release_free_memory_returns_the_heaps_holes() -> None:
    """Freed mid-sized blocks below a live one stay resident under glibc until `release_free_memory` hands their
    pages back (the pipeline calls it between stages)."""
    out = subprocess.run([sys.executable, "-c", TRIM_PROBE], capture_output=True, text=True, timeout=60)
    before, after = map(float, out.stdout.split())
    assert before - after > 48, (before, after, out.stderr)


def test_an_unforeseen_failure_is_one_error_line_and_the_debug_variable_shows_the_traceback(tmp_path, capsys,
                                                                                           monkeypatch):
    """A bug no check foresaw (here: a reader that raises RuntimeError) ends in one `error:` line and exit 2;
    HGCA_DEBUG=1, which `hgca --help` names, adds the traceback."""
    import numpy as np

    import hgca_core.io.sequence as sequence
    from hgca_core.cli import DEBUG_ENV, main

    def broken(*args, **kwargs):
        raise RuntimeError("reader bug\nsecond line")

    np.savez(tmp_path / "s.npz", points=np.zeros((5, 3)))
    monkeypatch.setattr(sequence, "read_inputs", broken)
    monkeypatch.delenv(DEBUG_ENV, raising=False)
    argv = ["read", str(tmp_path / "s.npz"), "-o", str(tmp_path / "o.npz")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [f"hgca read: error: unexpected RuntimeError: reader bug (set {DEBUG_ENV}=1 for the "
                                "traceback)"], err
    monkeypatch.setenv(DEBUG_ENV, "1")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and "RuntimeError: reader bug" in err
    assert err.splitlines()[-1].startswith("hgca read: error: unexpected RuntimeError")
    assert not (tmp_path / "o.npz").exists()
    res = subprocess.run([sys.executable, "-m", "hgca_core.cli", "--help"], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0 and f"{DEBUG_ENV}=1" in res.stdout


def test_memory_errors_and_full_disks_name_themselves():
    import errno

    from hgca_core.cli import unexpected

    assert unexpected(MemoryError()).startswith("out of memory")
    full = OSError(errno.ENOSPC, "No space left on device", "/mnt/x.npz")
    assert unexpected(full) == "no space left on the device (/mnt/x.npz); nothing was written"


PEAK_PROBE = """
from hgca_core.hardware import peak_rss_bytes
block = bytearray(200 * 2**20)
for i in range(0, len(block), 4096):
    block[i] = 1
print(peak_rss_bytes() / 2**20)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the spawn's inherited peak is Linux's accounting")
def test_peak_rss_is_the_processs_own_not_its_spawning_parents() -> None:
    """A worker's reported peak (tiles, `hgca bench`) is its own 200 MiB, not the 1 GiB its parent held when it
    spawned the worker, which getrusage's ru_maxrss would report."""
    ballast = bytearray(2**30)
    for i in range(0, len(ballast), 4096):
        ballast[i] = 1
    out = subprocess.run([sys.executable, "-c", PEAK_PROBE], capture_output=True, text=True, timeout=60)
    del ballast
    assert 200 <= float(out.stdout.strip()) < 600, out.stderr
