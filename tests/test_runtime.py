"""The persistent compilation cache: a second run with the same settings compiles nothing."""

import json
import re
import subprocess
import sys
import textwrap
import time

import jax
import jaxlib
import numpy as np
import pytest
from jax._src.lru_cache import LRUCache

from mbavo_jax.config import RuntimeConfig
from mbavo_jax.runtime import cache_folder, enable_compilation_cache, machine_key

pytestmark = pytest.mark.slow


def _track(seq, out, *overrides) -> dict:
    cmd = [sys.executable, "-m", "mbavo_jax.cli", "track", str(seq), "--out", str(out), "--quiet", "--format", "json",
           "--set", "tracker.n=4"]
    for o in overrides:
        cmd += ["--set", o]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    seq = tmp_path_factory.mktemp("seq")
    done = subprocess.run([sys.executable, "-m", "mbavo_jax.cli", "synth", "--out", str(seq), "--preset", "strong", "--frames", "3",
                           "--width", "160", "--height", "120", "--quiet"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return seq


def test_second_run_loads_every_program_from_the_cache(tiny, tmp_path):
    cache = tmp_path / "cache"
    first = _track(tiny, tmp_path / "a", f"runtime.cache_dir={cache}")
    assert first["compiled"] > 10 and first["startup_s"] > 0
    assert any(cache.iterdir())
    second = _track(tiny, tmp_path / "b", f"runtime.cache_dir={cache}")
    assert second["compiled"] == 0
    assert second["cache_hits"] >= first["compiled"]
    assert second["ate_rmse_m"] == pytest.approx(first["ate_rmse_m"], rel=1e-5, abs=1e-7)


def test_cache_off_compiles_and_writes_nothing(tiny, tmp_path):
    cache = tmp_path / "cache"
    off = _track(tiny, tmp_path / "a", f"runtime.cache_dir={cache}", "runtime.compilation_cache=false")
    assert off["compiled"] > 10 and off["cache_hits"] == 0
    assert not cache.exists()


def test_cache_folder_follows_the_settings_and_xdg(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    key = machine_key()
    assert key.startswith(f"jaxlib-{jaxlib.__version__}-") and key == machine_key()
    assert cache_folder() == tmp_path / "xdg" / "mbavo_jax" / "jax" / key
    assert cache_folder(RuntimeConfig(cache_dir=str(tmp_path / "c"))) == tmp_path / "c" / key
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert enable_compilation_cache(RuntimeConfig(cache_dir=str(blocker / "sub"))) is None  # one note, no crash
    assert enable_compilation_cache(RuntimeConfig(compilation_cache=False)) is None


def test_a_process_never_reads_a_program_another_is_still_writing(tmp_path):
    """JAX writes a cache entry in place; without its file lock (no size limit) a second process reads
    it half-written. With the settings enable_compilation_cache applies, every read is whole."""
    folder = enable_compilation_cache(RuntimeConfig(cache_dir=str(tmp_path)))
    try:
        _read_while_another_process_writes(folder)
    finally:
        enable_compilation_cache(RuntimeConfig(compilation_cache=False))


def _read_while_another_process_writes(folder) -> None:
    limit = jax.config.jax_compilation_cache_max_size
    assert limit == RuntimeConfig().cache_max_mb * 2**20
    size = 64 * 2**20
    writer = textwrap.dedent(f"""
        from jax._src.lru_cache import LRUCache
        LRUCache({str(folder)!r}, max_size={limit}).put("k", b"x" * {size})
    """)
    cache = LRUCache(str(folder), max_size=limit)
    proc = subprocess.Popen([sys.executable, "-c", writer])
    lengths, start = set(), time.monotonic()
    while time.monotonic() - start < 120:
        value = cache.get("k")
        if value is not None:
            lengths.add(len(value))
            if len(value) == size or proc.poll() is not None and len(value) != size:
                break
    assert proc.wait(timeout=120) == 0
    assert lengths == {size}


def test_a_run_first_releases_the_programs_of_earlier_runs_near_the_memory_map_limit(tiny, tmp_path):
    """XLA maps each compiled program's code apart, so one process that runs many settings and image
    sizes (``mbavo bench mono``) used to die in LLVM past ``vm.max_map_count``. A run now releases the
    process's programs first when their maps pass ``runtime.release_programs_at`` of the limit; the
    second run here (limit fraction tiny) releases the first's, reloads them and tracks the same."""
    script = textwrap.dedent(f"""
        import json, sys
        from mbavo_jax.config import RunConfig
        from mbavo_jax.datasets import open_sequence
        from mbavo_jax.odometry import run_odometry
        from mbavo_jax.runtime import make_room_for_programs, memory_maps
        held, limit = memory_maps()
        assert not make_room_for_programs(RunConfig().runtime), (held, limit)  # a fresh process is far below
        seq = open_sequence({str(tiny)!r})
        config = RunConfig().replace(tracker=dict(n=4), runtime=dict(release_programs_at=1e-6, cache_dir={str(tmp_path / "cache")!r}))
        first = run_odometry(seq, {str(tmp_path / "a")!r}, config, progress=False)
        after_first = memory_maps()[0]
        second = run_odometry(seq, {str(tmp_path / "b")!r}, config, progress=True)
        print(json.dumps(dict(after_first=after_first, tracked=[first["tracked"], second["tracked"]], hits=second["cache_hits"],
                              compiled=second["compiled"])))
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    notes = re.findall(r"released the compiled programs .*\((\d+) of the system's \d+ memory maps held, (\d+) now\)", done.stderr)
    assert len(notes) == 1, done.stderr  # the first run releases quietly (progress off); the second says so once
    held_before, held_after = map(int, notes[0])
    assert held_before >= out["after_first"] - 100 and held_before - held_after > 1000  # the first run's programs were let go
    assert out["compiled"] == 0 and out["hits"] > 10  # and came back from the compilation cache
    a, b = (np.loadtxt(tmp_path / run / "trajectory.txt") for run in "ab")
    assert out["tracked"][0] == out["tracked"][1] == len(a) and np.allclose(a, b, atol=1e-6)


def test_freed_heap_memory_goes_back_to_the_system_only_when_released():
    """Blocks freed in the middle of the heap stay resident (glibc keeps them for reuse) until
    ``release_free_memory`` hands them back: what keeps a long run's memory flat (runtime.trim_memory)."""
    script = textwrap.dedent("""
        import json
        from mbavo_jax.runtime import release_free_memory, resident_mb
        base = resident_mb()
        blocks = [bytearray(4096) for _ in range(40000)]  # about 160 MiB below glibc's mmap threshold
        kept = blocks[15::16]  # every 16th block (the last one too) pins the heap around the freed ones
        del blocks
        freed = resident_mb()
        released = release_free_memory()
        print(json.dumps({"base": base, "freed": freed, "released": released, "after": resident_mb(), "kept": len(kept)}))
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    r = json.loads(done.stdout)
    assert r["released"] is True
    assert r["freed"] - r["base"] > 120, r  # freed but still resident
    assert r["freed"] - r["after"] > 100, r  # handed back
