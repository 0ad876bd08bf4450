"""Compiled programs kept on disk by the library, so that a later process does not
compile them again.

Two kinds of entry, each compiled once, serialized (`jax.experimental.
serialize_executable`) and loaded in a fraction of a second after:

- `call`: programs that do not depend on the Lagrangian (the compact tier,
    `lagrax._period.tier`), keyed on the library's source, the static configuration
    and the arguments' shapes, without tracing anything: one executable serves every
    Lagrangian (entries `t*.bin`). Those made by `program` (`simulate_batch`'s),
    where XLA would split their loops across threads in this process, are compiled
    in a process of their own that keeps them whole (`lagrax._cache.apart`).
- `cached_call`: any compiled program of an eager call (the period sweep, the
    batched trajectories), keyed on the text of the lowered program itself (which
    holds everything it computes: a rebuilt Lagrangian with new parameter values that
    reach it as arguments lowers to the same text) and the compile options. A script
    run again, or a notebook restarted, loads them instead of compiling (seconds
    for a first sweep on a CPU core), as heyoka.py's on-disk cache of compiled code does
    (entries `p*.bin`). `compile_later` compiles such a program in a worker
    process on an idle core while the caller's tier goes on (the compact
    program), and names the entry by the call's pre-key.

Finding a `cached_call` entry by its lowered text costs the tracing and lowering of
the whole program (seconds for a sweep). A later process finds it without them, by
its **pre-key**: a digest of everything that determines the lowered text, computed
from the call's inputs alone: the library's source digest; the versions of Python,
jax, jaxlib, diffrax, equinox, lineax, optimistix, numpy, ml_dtypes; JAX's
configuration (every option but those of its persistent cache, and JAX's own list of
what enters a trace, context managers included); equinox's; the `JAX_`, `XLA_`,
`EQX_`, `LAGRAX_` and `TF_` environment variables; the devices and host CPU; the
module-level library function that made the jitted function and its arguments (for
the sweep: the canonical Lagrangian's jaxpr, the kernel's `Method`, the devices);
the compile options; the arguments' tree and abstract values (shape, dtype, weak
type, placement, layout). Every part is written by `lagrax._cache.faithful.text`, which
admits only kinds whose text says all of them and refuses any other (a function, a
closure's `custom_jvp` rule, a user's type, an object compared by identity): then
the call has no pre-key and finds its entry by lowering, as before, never by a
key that could name another program. A file `k*.key` holds the program key (and
the output structure, where it pickles) that a pre-key names; it is written where
the program's entry is on disk and its argument structure, derived from the
arguments, is the lowered program's. A pre-key that names an entry no longer there,
or one that fails to load, falls back to lowering (and is written again). Small
answers that cost a trace (whether the Taylor step covers a Lagrangian) are kept the
same way (`remembered`, files `d*.key`).

What is written is only what is known to load safely in another process
(`_kernels`): a program whose native code calls nothing outside XLA's own kernels,
or only jaxlib's LAPACK kernels, which a new process sets up before loading it
(`lagrax._compat.prepare_lapack`); a host callback (a progress meter, a
`jax.pure_callback`: a pointer into the process that compiled it), a transfer to or
from the host, or any kernel of unknown kind keeps the program in this process's
table only. The folder, its entries and their checks before loading are
`lagrax._cache.folder`'s (the folder is its owner's alone, each entry carries its
size, digest and kernels; `lagrax cache info|clear`).

The library never touches JAX's global configuration (its persistent compilation
cache stays the user's choice): this is its own cache, in `$LAGRAX_CACHE_DIR` or else
`$XDG_CACHE_HOME/lagrax/executables` (`~/.cache/...`); `LAGRAX_CACHE_DIR=""` turns
it off; so does running as one of several processes (`jax.distributed`), where an
executable belongs to one process's devices, and a default backend other than the
CPU. Every key also holds the JAX and jaxlib versions, `XLA_FLAGS`, the devices and
the host CPU (an executable is native code for one processor). An entry that cannot
be read is compiled again; past `folder.MAX_BYTES` the least recently used entries
are removed.

Nothing is written while JAX's own persistent compilation cache
(`jax_compilation_cache_dir`) is on or has served the process: an executable JAX
took from it serializes again without its object code on CPU, which XLA loads
without complaint, to fail at its first kernel (`NOT_FOUND: Function ... not
found`); that cache keeps programs for later processes itself. As a safety net,
the first call of an executable loaded from disk waits for its result: where it
fails with an error, the entry is removed and the program compiled, written and run
again (no program here donates its inputs, so the second run sees the same
arguments). A crash cannot be caught that way: what is written is what is known to
load safely, and `tests/test_cache_processes.py` runs every kind of program the
cache keeps in two fresh processes.
"""

import collections
import functools
import hashlib
import os
import pickle
import re
import sys
import threading
import weakref

import jax
import numpy as np
from jax.experimental import serialize_executable

from .. import _compat
from . import apart, faithful, folder as _folder


# Compiled programs of this process: by key (`call`), and by program and argument
# types (`cached_call`), most recently used last; each as (executable, the key of
# the disk entry it was loaded from until its first call has run, else None).
_LOADED: dict = {}
_PROGRAMS: collections.OrderedDict = collections.OrderedDict()
_MAX_PROGRAMS = 64
# What the cache did in this process: entries `loaded` from disk, programs `compiled`,
# entries `written`, programs `refused` (not written: not known to load safely).
STATS: collections.Counter = collections.Counter()


def cache_dir() -> str | None:
    """The folder executables are kept in (created, and checked to be this user's
    alone: `folder.folder`), or None when the cache is off or refused."""
    return _folder.folder()


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


@functools.lru_cache(maxsize=1)
def _host() -> str:
    """The processor the native code is compiled for: its model and features."""
    try:
        with open("/proc/cpuinfo") as fh:
            lines = [ln for ln in fh if ln.startswith(("model name", "flags"))]
        return "".join(sorted(set(lines)))
    except OSError:
        import platform

        return platform.processor() + platform.machine()


def _environment():
    devices = [(d.platform, d.device_kind, d.id) for d in jax.devices()]
    return (
        jax.__version__,
        jax.lib.__version__,
        os.environ.get("XLA_FLAGS", ""),
        devices,
        _host(),
    )


def _key(static, args) -> str:
    avals = [
        (getattr(x, "shape", ()), str(jax.numpy.result_type(x)))
        for x in jax.tree.leaves(args)
    ]
    text = repr(
        (
            _source_digest(),
            _environment(),
            repr(static),
            jax.tree.structure(args),
            avals,
        )
    )
    return "t" + hashlib.sha256(text.encode()).hexdigest()


# The plain function and compile options of each program made by `program`.
_PLAIN: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def program(fun, options=None, loop_bytes=None):
    """`jax.jit(fun, compiler_options=options)`, for `call`: where XLA would split
    its loops across threads in this process, or with `loop_bytes`, `call` compiles
    it in a process of its own that does not (`lagrax._cache.apart`), from `fun`
    itself (a jitted function with compile options cannot be called inside
    another); `loop_bytes`: there each while loop whose iteration reads and writes
    fewer bytes compiled as one function, its ops not dispatched one by one. Worth
    a second more of compile for a program of many short loops run often and
    compiled once per machine (the compact tiers': on an idle second core its split
    loops gain little, on a busy one they wait), not for `cached_call`'s programs,
    compiled per Lagrangian."""
    jitted = jax.jit(fun, compiler_options=options)
    # (`jax.jit(fun)`, called inside the exported program, finds `fun`'s trace.)
    _PLAIN[jitted] = (jax.jit(fun), dict(options or {}), loop_bytes)
    return jitted


def call(jitted, static, out_tree, *args):
    """`jitted(*args)` through an executable compiled once per machine: from this
    process's table, else from disk, else compiled (and written to disk).
    `static`: what besides the arguments' shapes determines the program (its
    `repr` must say it all); `out_tree`: the structure of its outputs (a pytree
    definition does not survive pickling: an `equinox.Module`'s holds sentinels).
    A `jitted` made by `program` is compiled apart where that pays (`program`)."""
    if not applies():
        return jitted(*args)
    key = _key(static, args)
    if key not in _LOADED:
        in_tree = jax.tree.structure((args, {}))
        compiled = _load(key, in_tree, out_tree)
        if compiled is None:
            compiled = _compile_apart(key, jitted, args, in_tree, out_tree)
        if compiled is not None:
            _LOADED[key] = (compiled, key)  # (its first run is checked: `_run`)
        else:
            _LOADED[key] = (_compile(key, jitted.lower(*args)), None)
    return _run(_LOADED, key, args, lambda: _compile(key, jitted.lower(*args)))


def _compile_apart(key, jitted, args, in_tree, out_tree):
    """`jitted(*args)` compiled in a process of its own (`apart`), loaded here and
    written under `key` where it is known to load safely; None where this process
    compiles it (`jitted` not made by `program`, nothing to gain apart, JAX's
    persistent cache is in use, or the worker failed)."""
    plain = _PLAIN.get(jitted)
    if plain is None or _jax_cache_in_use():
        return None
    fun, options, loop_bytes = plain
    if loop_bytes is None and not apart.wanted():
        return None
    payload = apart.compile_apart(fun, options, args, loop_bytes=loop_bytes)
    if payload is None:
        return None
    try:
        compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    except Exception:  # noqa: BLE001 -- compiled here instead
        return None
    STATS["compiled apart"] += 1
    if _path(key) is not None:
        _write(key, payload, _kernels(compiled))
    return compiled


def call_available(static, *args) -> bool:
    """Whether `call(jitted, static, out_tree, *args)` would run its program
    without compiling it: compiled or loaded in this process, or on disk."""
    key = _key(static, args)
    if key in _LOADED:
        return True
    if not applies():
        return False
    path = _path(key)
    return path is not None and os.path.exists(path)


def applies() -> bool:
    """Whether executables are kept on disk here: one process (an executable holds
    one process's devices) on a CPU (the only backend they were tested on)."""
    return jax.process_count() == 1 and jax.default_backend() == "cpu"


def _signature(x):
    """What the lowering of `x` depends on (cheap: this runs on every call)."""
    dtype = getattr(x, "dtype", None)
    if dtype is None:  # a Python scalar
        return type(x)
    return (
        type(x),
        getattr(x, "shape", ()),  # (JAX's typed Python scalars have none)
        dtype,
        getattr(x, "weak_type", False),
        getattr(x, "sharding", None),
    )


def cached_call(jitted, options, *args, n_static=0, origin=None, out_tree=None):
    """`jitted(*args)` (all of `args` concrete; the first `n_static` are `jitted`'s
    static arguments) through the executable of its lowered program: from this
    process's table, else from disk, else compiled and written to disk.
    `options`: the `compiler_options` `jitted` was made with (they are not in the
    lowered text). `origin`: `(factory, *arguments)`, a module-level function of the
    library with `factory(*arguments) is jitted`: with it, a later process finds the
    entry by its pre-key, without tracing (module docstring). `out_tree`: the
    structure of `jitted`'s outputs, where a pickled one is not equal to it (an
    `equinox.Module`'s)."""
    static, dynamic = args[:n_static], args[n_static:]
    leaves, treedef = jax.tree.flatten(dynamic)
    program = (jitted, static, treedef, tuple(_signature(x) for x in leaves))
    found = None
    if program not in _PROGRAMS:
        if cache_dir() is None or not applies():
            return jitted(*args)
        found = _Found(jitted, options, args, n_static, out_tree)
        found.prekey = _prekey(jitted, origin, options, static, leaves, treedef)
        _PROGRAMS[program] = found.entry()
        if len(_PROGRAMS) > _MAX_PROGRAMS:
            _PROGRAMS.popitem(last=False)
    else:
        _PROGRAMS.move_to_end(program)
    if found is None:
        found = _Found(jitted, options, args, n_static, out_tree)
    return _run(_PROGRAMS, program, dynamic, found.compile)


def available(jitted, options, *args, n_static=0, origin=None) -> bool:
    """Whether `cached_call` (same arguments) would run the program without
    compiling it: compiled in this process, or on disk under its pre-key (found
    without tracing; an entry found only by lowering counts as not available)."""
    static, dynamic = args[:n_static], args[n_static:]
    leaves, treedef = jax.tree.flatten(dynamic)
    program = (jitted, static, treedef, tuple(_signature(x) for x in leaves))
    if program in _PROGRAMS:
        return True
    if cache_dir() is None or not applies():
        return False
    prekey = _prekey(jitted, origin, options, static, leaves, treedef)
    if prekey is None:
        return False
    linked = _read_link(prekey)
    return linked is not None and os.path.exists(_path(linked[0]))


# ------------------------------------------------------------ compiled later


class _Later:
    """One program of `cached_call` compiled by `compile_later`: `state` is
    "running", "done" (on disk, named by its pre-key) or "failed"."""

    def __init__(self):
        self.state = "running"
        self.worker = None
        self.thread = None

    def stop(self):
        """Kills the worker and waits for the thread (what remains of it after the
        kill is short: the end of an export, or noticing the worker died)."""
        worker = self.worker
        if worker is not None and worker.poll() is None:
            worker.kill()
        if self.thread is not None:
            self.thread.join(timeout=60)


# Programs compiled later, by pre-key (one at a time in a process).
_LATER: dict = {}
_LATER_LOCK = threading.Lock()


def later_state(jitted, options, *args, n_static=0, origin=None) -> str | None:
    """The state of `compile_later`'s job for this `cached_call` (`_Later`), or
    None where none was started."""
    if not _LATER:  # (the pre-key costs a faithful text of the call: skipped)
        return None
    prekey = _call_prekey(jitted, options, args, n_static, origin)
    job = None if prekey is None else _LATER.get(prekey)
    return None if job is None else job.state


def compile_later(
    plain, jitted, options, *args, n_static=0, origin=None, out_tree=None
) -> str | None:
    """Starts compiling the program of `cached_call(jitted, options, *args, ...)`
    in a process of its own (`lagrax._cache.apart`), on a core this process leaves
    idle, while this process goes on (a tier that runs the call meanwhile, the
    compact program); the executable is written to disk and named by the call's
    pre-key, so that `available` turns True and `cached_call` loads it, here and in
    later processes. `plain`: a function of the dynamic arguments (`args[n_static:]`)
    computing the same program, without compile options. Returns the job's state
    (`_Later`), or None where none is started: the disk cache off, no pre-key, a
    process that may use one core (or as many as it has CPU devices), JAX's
    persistent cache in use, `LAGRAX_BACKGROUND=0`, or another job running. A job
    still running when the process exits is stopped (its worker killed)."""
    if os.environ.get("LAGRAX_BACKGROUND", "1").strip() == "0":
        return None
    if not applies() or cache_dir() is None or _jax_cache_in_use():
        return None
    if _usable_cores() <= jax.local_device_count():
        return None
    prekey = _call_prekey(jitted, options, args, n_static, origin)
    if prekey is None:
        return None
    with _LATER_LOCK:
        if prekey in _LATER:
            return _LATER[prekey].state
        if any(job.state == "running" for job in _LATER.values()):
            return None
        if not _LATER:
            import atexit

            atexit.register(_stop_later)
        job = _LATER[prekey] = _Later()
    job.thread = threading.Thread(
        target=_compile_later,
        args=(job, prekey, plain, (jitted, options, args, n_static, origin), out_tree),
        name="lagrax-compile-later",
        daemon=True,
    )
    job.thread.start()
    return job.state


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # (no affinity here: the machine's count)
        return os.cpu_count() or 1


def _call_prekey(jitted, options, args, n_static, origin):
    static, dynamic = args[:n_static], args[n_static:]
    leaves, treedef = jax.tree.flatten(dynamic)
    return _prekey(jitted, origin, options, static, leaves, treedef)


def _compile_later(job, prekey, plain, call, out_tree):
    """The thread of a `compile_later` job: the program exported here (traced and
    lowered: the Python part, while the caller's thread runs compiled code), compiled
    by the worker, loaded once to check what it calls, written, then named by the
    pre-key (with its output structure, where the caller does not give it). `call`:
    `(jitted, options, args, n_static, origin)`."""
    jitted, options, args, n_static, origin = call
    dynamic = args[n_static:]
    try:
        # (A thread traces under JAX's global settings, not the caller's context
        # managers: where those enter the program, the pre-keys differ.)
        if _call_prekey(jitted, options, args, n_static, origin) != prekey:
            raise RuntimeError("another trace context")
        started = lambda worker: setattr(job, "worker", worker)
        payload = apart.compile_apart(plain, options or {}, dynamic, started)
        if payload is None:
            raise RuntimeError("not compiled")
        in_tree = jax.tree.structure((dynamic, {}))
        found = jax.tree.structure(jax.eval_shape(plain, *dynamic))
        if out_tree is None:
            if pickle.loads(pickle.dumps(found)) != found:
                raise RuntimeError("an output structure that does not pickle")
            linked = found
        elif out_tree == found:
            linked = None  # (the caller's, given at every call)
        else:
            raise RuntimeError("another output structure")
        compiled = serialize_executable.deserialize_and_load(payload, in_tree, found)
        key = "p" + hashlib.sha256(f"later {prekey}".encode()).hexdigest()
        _write(key, payload, _kernels(compiled))
        if not os.path.exists(_path(key)):
            raise RuntimeError("not written")
        _folder.write(_path(prekey, ".key"), pickle.dumps((key, linked)))
        STATS["compiled later"] += 1
        job.state = "done"
    except Exception:  # noqa: BLE001 -- the caller's tiers go on as before
        job.state = "failed"


def _stop_later():
    for job in list(_LATER.values()):
        job.stop()


class _Found:
    """The executable of one program of `cached_call`: by its pre-key (no tracing),
    else by its lowered text; or compiled."""

    def __init__(self, jitted, options, args, n_static, out_tree):
        self.jitted, self.options, self.args = jitted, options, args
        self.n_static, self.out_tree = n_static, out_tree
        self.prekey = None

    @property
    def in_tree(self):
        return jax.tree.structure((self.args[self.n_static :], {}))

    def entry(self):
        """`(executable, key of its disk entry)`, the key None where compiled here."""
        linked = None if self.prekey is None else _read_link(self.prekey)
        if linked is not None:
            key, out_tree = linked
            out_tree = self.out_tree if out_tree is None else out_tree
            if out_tree is not None:
                compiled = _load(key, self.in_tree, out_tree)
                if compiled is not None:
                    return compiled, key
        lowered = self.jitted.lower(*self.args)
        key = _program_key(lowered, self.options)
        # (An entry the pre-key named and that did not load is not tried again.)
        if linked is None or linked[0] != key:
            compiled = _load(key, lowered.in_tree, lowered.out_tree)
            if compiled is not None:
                self._link(key, lowered)
                return compiled, key
        return self._compile(key, lowered), None

    def compile(self):
        """The program compiled (after a loaded executable failed), written under
        the key of its lowered text."""
        lowered = self.jitted.lower(*self.args)
        return self._compile(_program_key(lowered, self.options), lowered)

    def _compile(self, key, lowered):
        compiled = _compile(key, lowered)
        self._link(key, lowered)
        return compiled

    def _link(self, key, lowered):
        """Records pre-key → `key` where the entry is on disk, and where what the
        pre-key path loads with (the argument structure, derived from the arguments,
        and the output structure, pickled or given) is the lowered program's."""
        path = _path(key)
        if self.prekey is None or path is None or not os.path.exists(path):
            return
        if self.in_tree != lowered.in_tree:
            return
        out_tree = lowered.out_tree
        try:
            pickled = pickle.loads(pickle.dumps(out_tree)) == out_tree
        except Exception:  # noqa: BLE001 -- a node type that does not pickle
            pickled = False
        if not pickled:
            if self.out_tree is None or self.out_tree != out_tree:
                return
            out_tree = None  # (the caller's, given at every call)
        _folder.write(_path(self.prekey, ".key"), pickle.dumps((key, out_tree)))


def _prekey(jitted, origin, options, static, leaves, treedef):
    """The pre-key of a program: a digest of everything that determines its lowered
    text, computed without tracing it; None where a part has no faithful text
    (module docstring)."""
    if origin is None or not _library_function(origin[0]):
        return None
    try:
        if origin[0](*origin[1:]) is not jitted:
            return None
        parts = (
            faithful.text(options),
            faithful.text(tuple(static)),
            _tree_text(treedef),
            [_leaf_text(x) for x in leaves],
        )
        return _digest("k", origin, parts)
    except Exception:  # noqa: BLE001 -- no faithful text, or JAX's private trace
        return None  # context moved: no pre-key (found by lowering), never a wrong one


def _library_function(f) -> bool:
    module = getattr(f, "__module__", None) or ""
    return module.startswith("lagrax.") and faithful.module_level(f)


def _digest(prefix, origin, parts) -> str:
    """A digest of `origin` (`(function, *arguments)`) and `parts` with everything
    outside them that the library's results depend on; `faithful.Unfaithful` where
    a part has no faithful text."""
    function, *arguments = origin
    text = repr(
        (
            _source_digest(),
            _versions(),
            _environment(),
            _settings(),
            f"{function.__module__}.{function.__qualname__}",
            faithful.text(tuple(arguments)),
            parts,
        )
    )
    return prefix + hashlib.sha256(text.encode()).hexdigest()


def remembered(origin, compute) -> bool:
    """`compute()`, a bool that `origin` (`(function, *arguments)`, a module-level
    function of the library and what it is called with) determines, kept on disk
    under a digest of `origin` where it has a faithful text (as a pre-key): a later
    process reads it instead of computing it."""
    path = None
    if cache_dir() is not None and applies() and _library_function(origin[0]):
        try:
            path = _path(_digest("d", origin, ()), ".key")
        except Exception:  # noqa: BLE001 -- as for a pre-key: computed, not kept
            path = None
    if path is not None:
        found = _folder.read(path)
        if found is not None and found[1] in (b"0", b"1"):
            return found[1] == b"1"
    value = compute()
    if path is not None and type(value) is bool:
        _folder.write(path, b"1" if value else b"0")
    return value


@functools.lru_cache(maxsize=1)
def _versions():
    """The versions of Python and of the libraries whose code the pre-key trusts
    (`faithful.ROOTS`; lagrax: its source digest)."""
    found = [sys.version, jax.lib.__version__]
    for root in faithful.ROOTS[1:]:
        module = sys.modules.get(root)
        found.append((root, getattr(module, "__version__", None)))
    return tuple(found)


# The environment variables a program may depend on (read by JAX, XLA, equinox, and
# the library).
_VARIABLES = ("JAX_", "XLA_", "EQX_", "LAGRAX_", "TF_")
# The library's variables that say where programs are kept or compiled, not what
# they are.
_NOT_SETTINGS = ("LAGRAX_CACHE_DIR", "LAGRAX_BACKGROUND")


def _settings():
    """Everything outside the program that changes how it traces and lowers: JAX's
    configuration (every option, and JAX's own list of what enters a trace, the
    context managers' values included), the environment variables (equinox's
    settings among them: it reads them at import)."""
    try:
        context = _compat.trace_context()
    except Exception as e:  # noqa: BLE001 -- JAX moved it: no pre-key
        raise faithful.Unfaithful(f"JAX's trace context ({e})") from None
    variables = {
        k: v
        for k, v in os.environ.items()
        if k.startswith(_VARIABLES) and k not in _NOT_SETTINGS
    }
    options = {k: v for k, v in jax.config.values.items() if not _cache_option(k)}
    return faithful.text((options, list(context), variables))


def _cache_option(name) -> bool:
    """JAX's options for its persistent compilation cache: where programs come from,
    not what they are (the CLI turns that cache on in its process)."""
    return "compilation_cache" in name or "persistent_cache" in name


def _tree_text(treedef) -> str:
    """A tree of tuples, lists, dicts and Nones, written out; other nodes refused."""
    data = treedef.node_data()
    if data is None:
        return "*"
    node, aux = data
    if node not in (tuple, list, dict, type(None)):
        raise faithful.Unfaithful(f"a pytree node {node}")
    children = ",".join(_tree_text(c) for c in treedef.children())
    return f"{node.__name__}{faithful.text(aux)}({children})"


def _leaf_text(x) -> str:
    """What a program's lowering takes from an argument: its abstract value and,
    for a JAX array, its placement and layout."""
    t = type(x)
    if t in (bool, int, float, complex):  # (weakly typed; the value an argument)
        return t.__name__
    if t is np.ndarray or isinstance(x, np.generic):
        return f"np({x.shape},{faithful.text(x.dtype)})"
    if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer):
        sharding = faithful.text(x.sharding)
        dtype = faithful.text(np.dtype(x.dtype))
        layout = repr(x.format.layout)
        return f"jax({x.shape},{dtype},{x.weak_type},{x.committed},{sharding},{layout})"
    aval = getattr(x, "aval", None)
    if t.__module__.startswith("jax.") and faithful.module_level(t) and aval:
        # (JAX's host literals, `TypedNdArray`, `TypedFloat`...: typed by their
        # abstract value, whatever the 64-bit mode)
        return f"{t.__qualname__}({faithful.aval_text(aval)})"
    raise faithful.Unfaithful(f"an argument of type {t}")


def _read_link(prekey):
    """`(program key, output structure or None)` recorded under `prekey`, or None."""
    found = _folder.read(_path(prekey, ".key"))
    if found is None:
        return None
    try:
        key, out_tree = pickle.loads(found[1])
    except Exception:  # noqa: BLE001 -- not a link: found by lowering
        return None
    if not (isinstance(key, str) and key.startswith("p")):
        return None
    if out_tree is not None and not isinstance(out_tree, jax.tree_util.PyTreeDef):
        return None
    return key, out_tree


def _program_key(lowered, options):
    text = repr((_environment(), repr(options), lowered.as_text()))
    return "p" + hashlib.sha256(text.encode()).hexdigest()


def _run(table, slot, call_args, recompile):
    """Runs `table[slot]`'s executable on `call_args`. The first call of one loaded
    from disk is waited for, so that a failure at run time shows here: its entry
    is then removed, and the program compiled again (`recompile()`, which writes
    it anew) and run. (An executable without its object code fails at its first
    kernel; one that lacks only some of it is refused at loading.)"""
    compiled, key = table[slot]
    if key is None:
        return compiled(*call_args)
    try:
        out = jax.block_until_ready(compiled(*call_args))
    except jax.errors.JaxRuntimeError:
        _remove(key)
        compiled = recompile()
        out = compiled(*call_args)
    table[slot] = (compiled, None)
    return out


# Programs JAX has taken from its persistent compilation cache in this process,
# counted from its monitoring events (listened to from the start: such an executable
# can come back later from JAX's in-memory cache, without an event).
_jax_cache_hits = 0


def _on_event(event, **kwargs):
    global _jax_cache_hits
    if event == _compat.JAX_CACHE_HIT_EVENT:
        _jax_cache_hits += 1


jax.monitoring.register_event_listener(_on_event)


def _compile(key, lowered):
    """`lowered.compile()`, written to disk under `key` unless JAX's persistent
    compilation cache is on or has served this process: an executable JAX took from
    it serializes without its object code, and that cache keeps programs for later
    processes itself."""
    compiled = lowered.compile()
    STATS["compiled"] += 1
    if not _jax_cache_in_use():
        _store(key, compiled)
    return compiled


def _jax_cache_in_use() -> bool:
    """Whether JAX's persistent compilation cache is on or has served this process."""
    on = jax.config.jax_compilation_cache_dir is not None
    return bool((on and jax.config.jax_enable_compilation_cache) or _jax_cache_hits)


def _path(key, suffix=".bin"):
    """Where the entry `key` is kept (`.bin`: an executable; `.key`: the program
    key a pre-key names)."""
    folder = cache_dir()
    return None if folder is None else os.path.join(folder, key + suffix)


def _remove(key):
    path = _path(key)
    if path is not None:
        _folder.remove(path)


# The custom calls of a CPU executable known to load safely in another process:
# jaxlib's LAPACK kernels (Cholesky, LU, triangular solves), once set up there.
_LAPACK = re.compile(r"lapack_[sdcz][a-z0-9]+_ffi")
_HOST_TRANSFER = re.compile(r" (send|recv|infeed|outfeed)(-done)?\(")


def _kernels(compiled):
    """The targets of `compiled`'s custom calls (native code outside XLA's own) where
    each is known to load safely in another process; None where one is not (a host
    callback: a pointer into this process; anything unknown), or where the program
    moves data to or from the host. Refused unless shown safe."""
    text = compiled.as_text()
    if not isinstance(text, str):
        return None
    targets = re.findall(r'custom_call_target="([^"]*)"', text)
    if text.count(" custom-call(") != len(targets) or _HOST_TRANSFER.search(text):
        return None
    kinds = sorted(set(targets))
    if not all(_LAPACK.fullmatch(t) for t in kinds):
        return None
    if kinds and not _compat.prepare_lapack():
        return None
    return kinds


def _load(key, in_tree, out_tree):
    """The executable `key` from disk, or None where there is none, or it fails a
    check (`folder.read`), or it calls kernels that cannot be set up here."""
    path = _path(key)
    if path is None or not os.path.exists(path):
        return None
    found = _folder.read(path)
    if found is None or found[0].get("key") != key:
        _folder.remove(path)  # (damaged, or not ours: compiled and written anew)
        return None
    kinds = found[0].get("kernels")
    if not isinstance(kinds, list) or not all(
        isinstance(k, str) and _LAPACK.fullmatch(k) for k in kinds
    ):
        return None
    if kinds and not _compat.prepare_lapack():  # (before loading: see there)
        return None
    try:
        compiled = serialize_executable.deserialize_and_load(
            found[1], in_tree, out_tree
        )
    except Exception:  # noqa: BLE001 -- a stale entry: compile again
        return None
    STATS["loaded"] += 1
    return compiled


def _store(key, compiled):
    """Writes `compiled` under `key`, where it is known to load safely in another
    process (`_kernels`)."""
    if _path(key) is None:
        return
    kinds = _kernels(compiled)
    try:
        payload = None if kinds is None else serialize_executable.serialize(compiled)[0]
    except Exception:  # noqa: BLE001 -- a program that cannot be serialized
        payload = None
    _write(key, payload, kinds)


def _write(key, payload, kinds):
    """Writes `payload`, a serialized executable calling the kernels `kinds`, under
    `key`; None for either: refused (kept in this process's table only)."""
    path = _path(key)
    if path is None:
        return
    if payload is None or kinds is None:
        STATS["refused"] += 1
        return
    if _folder.write(path, payload, {"key": key, "kernels": kinds}):
        STATS["written"] += 1
        _folder.evict(os.path.dirname(path))
