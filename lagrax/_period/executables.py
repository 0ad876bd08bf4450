"""Compiled programs kept on disk by the library, for programs that do not depend
on the Lagrangian (the tape path, `lagrax._period.tier`).

The executable of such a program serves every Lagrangian and every later process
on the same machine: compiled once, serialized (`jax.experimental.
serialize_executable`), loaded in milliseconds after. The library never touches
JAX's global configuration (its persistent compilation cache stays the user's
choice): this is its own cache, in `$LAGRAX_CACHE_DIR` or else
`$XDG_CACHE_HOME/lagrax/executables` (`~/.cache/...`); `LAGRAX_CACHE_DIR=""` turns
it off. An entry is keyed on the library's source, the JAX and jaxlib versions, the
devices, the static configuration and the arguments' shapes; one that cannot be
read is compiled again.
"""

import functools
import hashlib
import os
import pickle
import tempfile

import jax
from jax.experimental import serialize_executable


# Compiled programs of this process, by key.
_LOADED: dict = {}


def cache_dir() -> str | None:
    """Where executables are kept, or None when the cache is off."""
    env = os.environ.get("LAGRAX_CACHE_DIR")
    if env is not None:
        return env or None
    base = os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache"))
    return os.path.join(base, "lagrax", "executables")


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    """A digest of the library's source: an executable compiled by other code is
    never loaded."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    h = hashlib.sha256()
    for folder, dirs, files in sorted(os.walk(root)):
        dirs.sort()
        for name in sorted(files):
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                h.update(os.path.relpath(path, root).encode())
                with open(path, "rb") as fh:
                    h.update(fh.read())
    return h.hexdigest()


def _key(static, args) -> str:
    devices = [(d.platform, d.device_kind, d.id) for d in jax.devices()]
    avals = [
        (getattr(x, "shape", ()), str(jax.numpy.result_type(x)))
        for x in jax.tree.leaves(args)
    ]
    text = repr(
        (
            _source_digest(),
            jax.__version__,
            jax.lib.__version__,
            devices,
            repr(static),
            jax.tree.structure(args),
            avals,
        )
    )
    return hashlib.sha256(text.encode()).hexdigest()


def call(jitted, static, out_tree, *args):
    """`jitted(*args)` through an executable compiled once per machine: from this
    process's table, else from disk, else compiled (and written to disk).
    `static`: what besides the arguments' shapes determines the program (its
    `repr` must say it all); `out_tree`: the structure of its outputs (a pytree
    definition does not survive pickling: an `equinox.Module`'s holds sentinels)."""
    key = _key(static, args)
    compiled = _LOADED.get(key)
    if compiled is None:
        compiled = _load(key, args, out_tree)
        if compiled is None:
            compiled = jitted.lower(*args).compile()
            _store(key, compiled)
        _LOADED[key] = compiled
    return compiled(*args)


def _path(key):
    folder = cache_dir()
    return None if folder is None else os.path.join(folder, key + ".bin")


def _load(key, args, out_tree):
    path = _path(key)
    if path is None or not os.path.exists(path):
        return None
    try:
        with open(path, "rb") as fh:
            payload = pickle.load(fh)
        in_tree = jax.tree.structure((args, {}))
        return serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    except Exception:  # noqa: BLE001 -- a damaged or stale entry: compile again
        return None


def _store(key, compiled):
    path = _path(key)
    if path is None:
        return
    try:
        payload = serialize_executable.serialize(compiled)[0]
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), suffix=".tmp")
        with os.fdopen(fd, "wb") as fh:
            pickle.dump(payload, fh)
        os.replace(tmp, path)
    except Exception:  # noqa: BLE001 -- a read-only or full disk: keep it in memory
        return
