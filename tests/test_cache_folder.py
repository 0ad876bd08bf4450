"""The disk cache trusts no one else: its folder is its owner's alone, a folder others
can write is refused with a warning naming it and the fix, and an entry is checked
before it is loaded (a damaged, altered or foreign one is compiled again); a program
that cannot load safely in another process is never written. `lagrax cache` shows and
empties it."""

import os
import stat
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lagrax._cache import executables, folder
from lagrax._cli.main import main


@pytest.fixture
def fresh(monkeypatch, without_jax_cache):
    """A process with an empty table of programs and its own counts."""
    import collections

    monkeypatch.setattr(executables, "_PROGRAMS", collections.OrderedDict())
    monkeypatch.setattr(executables, "STATS", collections.Counter())
    monkeypatch.setattr(folder, "_WARNED", set())

    def run(f, *args):
        monkeypatch.setattr(executables, "_PROGRAMS", collections.OrderedDict())
        return executables.cached_call(jax.jit(f), None, *args)

    return run


def _double(x):
    return 2 * x + 1


def _entries(path):
    return sorted(p for p in path.iterdir() if p.suffix == ".bin")


def test_a_new_folder_and_its_entries_are_the_owners_alone(
    monkeypatch, tmp_path, fresh
):
    where = tmp_path / "a" / "cache"
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(where))
    x = jnp.arange(3.0)
    np.testing.assert_array_equal(fresh(_double, x), 2 * x + 1)
    assert stat.S_IMODE(where.stat().st_mode) == 0o700
    (entry,) = _entries(where)
    assert stat.S_IMODE(entry.stat().st_mode) == 0o600
    assert executables.STATS["written"] == 1
    np.testing.assert_array_equal(fresh(_double, x), 2 * x + 1)
    assert executables.STATS["loaded"] == 1 and executables.STATS["compiled"] == 1


@pytest.mark.parametrize("how", ["group", "others", "parent"])
def test_a_folder_others_can_write_is_refused_with_a_warning(
    monkeypatch, tmp_path, fresh, how
):
    where = tmp_path / "cache"
    where.mkdir(mode=0o700)
    if how == "parent":
        os.chmod(tmp_path, 0o777)  # anyone may replace the folder
    else:
        os.chmod(where, 0o770 if how == "group" else 0o707)
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(where))
    x = jnp.arange(3.0)
    with pytest.warns(RuntimeWarning, match="chmod 700") as caught:
        out = fresh(_double, x)
    assert str(where) in str(caught[0].message)
    np.testing.assert_array_equal(out, 2 * x + 1)
    assert list(where.iterdir()) == [] and not executables.STATS  # (not used)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (warned once per folder)
        fresh(_double, x)
    os.chmod(tmp_path, 0o700)


@pytest.mark.skipif(
    not hasattr(os, "getuid") or os.getuid() != 0, reason="chown needs root"
)
def test_a_folder_or_entry_of_another_user_is_not_read(monkeypatch, tmp_path, fresh):
    where = tmp_path / "cache"
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(where))
    x = jnp.arange(4.0)
    fresh(_double, x)
    (entry,) = _entries(where)
    os.chown(entry, 12345, 12345)  # an entry someone else wrote
    np.testing.assert_array_equal(fresh(_double, x), 2 * x + 1)
    assert executables.STATS["loaded"] == 0 and executables.STATS["compiled"] == 2
    os.chown(where, 12345, 12345)  # the folder itself
    with pytest.warns(RuntimeWarning, match="another user"):
        np.testing.assert_array_equal(fresh(_double, x), 2 * x + 1)
    assert executables.STATS["loaded"] == 0


@pytest.mark.parametrize("damage", ["truncated", "flipped", "kernel", "garbage"])
def test_a_damaged_or_altered_entry_is_compiled_again(
    monkeypatch, tmp_path, fresh, damage
):
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    x = jnp.linspace(0.0, 1.0, 5)
    fresh(_double, x)
    (entry,) = _entries(tmp_path)
    blob = entry.read_bytes()
    if damage == "truncated":
        blob = blob[: len(blob) // 2]
    elif damage == "flipped":
        blob = blob[:-100] + bytes([blob[-100] ^ 1]) + blob[-99:]
    elif damage == "kernel":  # a header claiming a kernel bound to its process
        blob = blob.replace(
            b'"kernels": []', b'"kernels": ["xla_ffi_python_cpu_callback"]'
        )
        assert b"python_cpu_callback" in blob
    else:
        blob = b"not an entry"
    entry.write_bytes(blob)
    np.testing.assert_array_equal(fresh(_double, x), 2 * x + 1)
    assert executables.STATS["loaded"] == 0 and executables.STATS["compiled"] == 2


def test_a_program_with_a_host_callback_is_never_written(monkeypatch, tmp_path, fresh):
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))

    def f(x):
        return jax.pure_callback(np.sin, jax.ShapeDtypeStruct(x.shape, x.dtype), x)

    x = jnp.arange(3.0)
    np.testing.assert_allclose(fresh(f, x), np.sin(x))
    assert _entries(tmp_path) == [] and executables.STATS["refused"] == 1
    # A LAPACK factorization is written, with its kernels named in the entry.
    a = jnp.array([[4.0, 1.0], [1.0, 3.0]])
    np.testing.assert_allclose(fresh(jnp.linalg.cholesky, a), np.linalg.cholesky(a))
    (entry,) = _entries(tmp_path)
    assert b"lapack_dpotrf_ffi" in entry.read_bytes().split(b"\n")[1]


def test_cache_info_and_clear(monkeypatch, tmp_path, fresh, capsys):
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path / "c"))
    assert main(["cache", "info"]) == 0
    assert "empty" in capsys.readouterr().out
    fresh(_double, jnp.arange(3.0))
    assert main(["cache", "info"]) == 0
    out = capsys.readouterr().out
    assert str(tmp_path / "c") in out and "1 files" in out and "state    on" in out
    (tmp_path / "c" / "notes.txt").write_text("not the cache's")
    assert main(["cache", "clear"]) == 0
    assert "removed 1 files" in capsys.readouterr().out
    assert [p.name for p in (tmp_path / "c").iterdir()] == ["notes.txt"]
    monkeypatch.setenv("LAGRAX_CACHE_DIR", "")
    assert main(["cache", "info"]) == 0
    assert "off" in capsys.readouterr().out
