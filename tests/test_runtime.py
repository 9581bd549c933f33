"""The persistent compilation cache: a second run with the same settings compiles nothing."""

import json
import subprocess
import sys
import textwrap
import time

import jax
import jaxlib
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
