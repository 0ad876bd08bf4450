import atexit
import os
import shutil
import tempfile

import jax
import pytest


# The library's disk cache of executables (`lagrax._cache.executables`) off, unless a
# test turns it on: tests compile what they check, and write nothing outside their
# temporary folders. XDG_CACHE_HOME: a folder of this run's own (the CLI's
# `--distributed` runs keep JAX's persistent compilation cache under it).
os.environ["LAGRAX_CACHE_DIR"] = ""
os.environ["XDG_CACHE_HOME"] = tempfile.mkdtemp(prefix="lagrax-tests-")
atexit.register(shutil.rmtree, os.environ["XDG_CACHE_HOME"], ignore_errors=True)

# XLA's thread pool for a program's loops: one thread (as in a process on one core),
# so that the programs the library compiles apart where XLA would split their loops
# (`lagrax._cache.apart`) are compiled in the tests' processes; the tests of that
# path start processes with a pool of two.
os.environ.setdefault("PJRT_NPROC", "1")

# No specialized program compiled later in a worker process (`executables.
# compile_later`) but where a test asks for it: it would change which tier a later
# call of a test takes.
os.environ["LAGRAX_BACKGROUND"] = "0"

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# Keep the suite honest on a 2-core CI machine: hypothesis examples are few but real.
from hypothesis import settings  # noqa: E402


settings.register_profile("ci", max_examples=25, deadline=None, derandomize=True)
settings.register_profile("dev", max_examples=50, deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")


@pytest.fixture
def key():
    return jax.random.key(5678)


@pytest.fixture
def without_jax_cache(monkeypatch):
    """JAX's persistent compilation cache off for the test: the CLI, called in this
    process by other tests, turns it on for the rest of the process, and while it
    is on (or has served the process) the library writes no executables."""
    from jax.experimental.compilation_cache import compilation_cache

    from lagrax._cache import executables as _executables

    folder = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", None)
    compilation_cache.reset_cache()
    jax.clear_caches()  # (no executable JAX took from that cache comes back)
    monkeypatch.setattr(_executables, "_jax_cache_hits", 0)
    yield
    jax.config.update("jax_compilation_cache_dir", folder)
    compilation_cache.reset_cache()


@pytest.fixture
def executable_cache(monkeypatch, tmp_path, without_jax_cache):
    """The library's disk cache of executables in a folder of the test's own:
    `(folder, loads, new_process)`, `loads` one bool per entry looked for on disk
    (found or not), `new_process()` empties this process's table of programs (as a
    later process starts)."""
    import collections

    from lagrax._cache import executables as _executables

    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(_executables, "_PROGRAMS", collections.OrderedDict())
    loads = []
    load = _executables._load

    def spy(key, in_tree, out_tree):
        out = load(key, in_tree, out_tree)
        loads.append(out is not None)
        return out

    monkeypatch.setattr(_executables, "_load", spy)

    def new_process():
        monkeypatch.setattr(_executables, "_PROGRAMS", collections.OrderedDict())

    return tmp_path, loads, new_process
