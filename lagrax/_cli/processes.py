"""JAX for the command: float64, the compilation cache, devices, other processes."""

import math
import os
import sys

from .parser import cpu_count, first_line, UsageError


class Unreachable(Exception):
    """The other processes of a distributed run could not be reached (exit 3)."""


def setup_jax(args):
    """Configures JAX before its backends start. Returns the devices to sweep over."""
    import jax

    jax.config.update("jax_enable_x64", True)
    # Compiling the sweep takes seconds; a later run loads it instead. One process
    # on a CPU: from the library's own disk cache (found without tracing). Several
    # processes (`--distributed`), whose executables it does not keep: from JAX's
    # persistent compilation cache, under the same folder.
    if args.distributed:
        cache = os.path.join(
            os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"),
            "lagrax",
            "jax",
        )
        try:
            os.makedirs(cache, mode=0o700, exist_ok=True)
            jax.config.update("jax_compilation_cache_dir", cache)
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
        except Exception:  # a read-only home: just compile every time
            pass
    wanted = args.devices if args.devices is not None else cpu_count()
    try:
        # Every core a host device: a CPU device runs one loop at a time, so one
        # device is one core. Ignored where the default backend is a GPU or TPU.
        # Called from Python (`main(argv)`), JAX's device count is the caller's
        # unless --devices says otherwise.
        if args.devices is not None or args.from_command_line:
            jax.config.update("jax_num_cpu_devices", wanted)
    except RuntimeError:
        # JAX already started in this process (the command called from Python): keep
        # its devices, unless more were asked for than it has.
        if args.devices is not None and args.devices > len(jax.local_devices()):
            raise UsageError(
                f"--devices {args.devices}: JAX is already running in this process "
                f"with {len(jax.local_devices())} device(s)"
            ) from None
    if args.distributed:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        kwargs = {}
        if args.coordinator is not None:
            kwargs = dict(
                coordinator_address=args.coordinator,
                num_processes=args.num_processes,
                process_id=args.process_id,
            )
        timeout = max(1, math.ceil(args.timeout))
        try:
            jax.distributed.initialize(
                **kwargs,
                initialization_timeout=timeout,
                heartbeat_timeout_seconds=timeout,
                shutdown_timeout_seconds=timeout,
            )
        except ValueError as e:  # no cluster detected and no flags
            raise UsageError(
                f"--distributed: {first_line(e)} (JAX found no cluster to join: give "
                "--coordinator HOST:PORT --num-processes N --process-id I)"
            ) from None
        except Exception as e:  # noqa: BLE001 - the runtime's own error types
            raise Unreachable(
                f"could not join the other processes at {args.coordinator or 'the'} "
                f"coordinator within {timeout} s: {first_line(e)}"
            ) from None
        # gloo announces its first connection on stdout, where the table goes: make
        # that connection now, with stdout sent to stderr.
        sys.stdout.flush()
        saved = os.dup(1)
        try:
            os.dup2(2, 1)
            broadcast(0)
        finally:
            os.dup2(saved, 1)
            os.close(saved)
        return jax.devices()
    devices = jax.local_devices()
    if args.devices is not None:
        devices = devices[: args.devices]
    return devices


def broadcast(value):
    """Process 0's int64 array on every process (JAX's collectives, nothing else)."""
    import jax
    import numpy as np

    if jax.process_count() == 1:
        return np.asarray(value)
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.broadcast_one_to_all(np.asarray(value)))
