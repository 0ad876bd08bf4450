"""A program compiled in a process of its own, whose XLA splits no loop across
threads (and, for the compact tiers' programs, runs each loop as one function).

XLA's CPU client splits each large loop of a program into parts run in parallel on
its thread pool, sized when JAX starts from the cores the process may use.
`simulate_batch`'s compact program runs thousands of short loops per call (its
blocks of the tape, order by order), so that handing the parts to the other threads
and waiting for them costs more than the parts themselves (`benchmarks/README.md`:
unsplit, it runs faster and on a third of the CPU time in a process that may use
every core). A process cannot resize its pool once JAX has started, so those
programs (`executables.program`, kept once per machine: they serve every Lagrangian
of their class) are compiled in a new process started with a pool of one thread
(`_compat.one_thread_environment`) and, since XLA dispatches each op of a loop's
iteration on its own unless a process-wide flag says otherwise, with their loops
compiled as one function each (`_compat.whole_loop_environment`: faster, on one
core too), from the program exported by `jax.export`; its
executable comes back serialized, is written to the disk cache and loaded here.
Anything that fails on the way (a program `jax.export` refuses, a worker that dies)
leaves the compile to this process, as before: only slower."""

import os
import pickle
import subprocess
import sys

import jax

from .. import _compat


_WORKER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "apart_worker.py")


def wanted() -> bool:
    """Whether a program compiled here would have its loops split (and compiling it
    apart would not: it runs on one device)."""
    return jax.local_device_count() == 1 and _compat.splits_loops()


def compile_apart(fun, options, args, started=None, loop_bytes=None) -> bytes | None:
    """The serialized executable of `jax.jit(fun, compiler_options=options)(*args)`,
    compiled in a new process with one XLA thread; None where that fails (the caller
    compiles the program itself). `fun` itself may be jitted (without options).
    `started(worker)`: called with the worker's `subprocess.Popen` once it runs
    (killing it makes this return None). `loop_bytes`: each while loop whose
    iteration reads and writes fewer bytes compiled as one function
    (`_compat.whole_loop_environment`: for programs of many short loops, not for
    unrolled ones)."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", **_compat.one_thread_environment())
    if loop_bytes is not None:
        env = _compat.whole_loop_environment(env, loop_bytes)
    env["JAX_ENABLE_X64"] = "1" if jax.config.jax_enable_x64 else "0"
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # (its executables lack object code)
    try:
        # Started first: it imports JAX while the program is exported here.
        worker = subprocess.Popen(
            [sys.executable, "-P", _WORKER],  # (-P: no lagrax/_cache on its path)
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
        )
    except Exception:  # noqa: BLE001 -- no interpreter to start (embedded Python)
        return None
    if started is not None:
        started(worker)
    try:
        leaves, treedef = jax.tree.flatten(args)
        # A flat signature: `jax.export` serializes trees of standard nodes only.
        flat = jax.jit(lambda *xs: jax.tree.leaves(fun(*treedef.unflatten(xs))))
        exported = jax.export.export(flat)(*leaves)
        if exported.nr_devices != 1:
            return None
        request = pickle.dumps((exported.serialize(), dict(options)))
        out, _ = worker.communicate(request)
        payload = pickle.loads(out) if worker.returncode == 0 else None
    except Exception:  # noqa: BLE001 -- not exportable (effects, callbacks...), or
        return None  # the worker failed: compiled here instead
    finally:  # (also where this process is interrupted)
        if worker.poll() is None:
            worker.kill()
            worker.wait()
    return payload if isinstance(payload, bytes) else None
