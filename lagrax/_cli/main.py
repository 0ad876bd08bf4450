r"""The `lagrax` command: `lagrax sweep [TARGET ...]` and `lagrax systems`.

`lagrax sweep` measures the period of many amplitudes at once with
`lagrax.sweep_periods` and compares it with a reference. TARGET is

- a built-in system of `lagrax.systems` (`lagrax systems` lists them), e.g.
  - pendulum: amplitude $\theta_0$ (radians from the downward vertical), exact
    $T = 2\pi\sqrt{r/g}/\mathrm{AGM}(1, \cos(\theta_0/2))$, $T_0 = 2\pi\sqrt{r/g}$;
  - cycloid (Huygens): amplitude $a = \pi - \theta_0$, the angle the generating circle
    has rolled from the bottom ($a = \pi$ is release at the cusp), integrated in the
    regular coordinate $u = \cos(\theta_0/2) = \sin(a/2)$; exact
    $T = T_0 = 4\pi\sqrt{R/g}$ for every amplitude;
- or your own Lagrangian of one coordinate, `module:attr` or `path/to/file.py:attr`
  (the convention of uvicorn and gunicorn), naming `L(q, qdot, t)` or a factory that
  returns one (`--param name=value` is passed to the factory); the amplitude is then the
  release point $q_0$ and the reference is `lagrax.quadrature_period` on request.

Parameters default to 1 (`g = r = R = 1`). Exit status: 0 all periods succeeded, 1 some
amplitudes failed (their status is in the table and file), 2 bad arguments, 3 the other
processes of a `--distributed` run could not be reached, 130 interrupted (rerun the same
command to resume from the checkpoints next to `--out`).
"""

import argparse
import ast
import importlib
import importlib.util
import inspect
import json
import math
import os
import re
import sys
import tempfile
import time
from dataclasses import dataclass, field


_SOLVERS = ("auto", "taylor", "dopri8", "dopri5", "tsit5")
_BLOCK_CHUNKS = 4  # chunks per device in a checkpoint/progress block
_QUADRATURE_BLOCK = 2048  # release points per quadrature call (bounded memory)
_PROBE_DOF = 6  # coordinates tried when telling the user how many L has


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, no usage dump, exit 2
        raise _UsageError(message)


def _cpu_count():
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _parser():
    p = _Parser(
        prog="lagrax",
        description="Lagrangian mechanics by automatic differentiation.",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.add_parser(
        "systems",
        help="list the built-in systems, their parameters and defaults",
        description="The built-in systems of lagrax.systems, one line each.",
    )
    s = sub.add_parser(
        "sweep",
        help="periods of many amplitudes against a reference",
        description=(
            "Period against amplitude, float64. TARGET: a built-in system (`lagrax "
            "systems` lists them; 'both' = pendulum and cycloid, the default) or your "
            "own Lagrangian of one coordinate as module:attr or path/to/file.py:attr, "
            "naming L(q, qdot, t) or a factory returning one."
        ),
    )
    s.add_argument(
        "targets",
        nargs="*",
        default=["both"],
        metavar="TARGET",
        help="built-in name, module:attr or file.py:attr (default: both)",
    )
    s.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="keyword for the system's factory, e.g. --param g=9.81 (repeatable)",
    )
    s.add_argument("--count", type=int, default=2048, help="amplitudes per system")
    s.add_argument(
        "--min",
        type=float,
        default=None,
        dest="amin",
        help="smallest amplitude (built-ins: rad, default 1e-3; your own L: the "
        "release point q0, required)",
    )
    s.add_argument(
        "--max",
        type=float,
        default=None,
        dest="amax",
        help="largest amplitude (default π − 1e-3 pendulum, π cycloid; required for "
        "your own L)",
    )
    s.add_argument(
        "--solver",
        default="auto",
        choices=_SOLVERS,
        help="auto (default): the library's default, Taylor where L's equations allow "
        "it and its program unrolls, Dopri8 otherwise",
    )
    s.add_argument("--rtol", type=float, default=1e-13)
    s.add_argument("--atol", type=float, default=1e-13)
    s.add_argument(
        "--max-steps",
        type=int,
        default=None,
        help="solver steps allowed per lane and leg (default: the library's)",
    )
    s.add_argument(
        "--method",
        default=None,
        choices=("matched", "quarter", "half", "full"),
        help="how much of each orbit to integrate (see lagrax.sweep_periods). Default "
        "'quarter' for the mirror-symmetric pendulum and cycloid (exact there and best "
        "conditioned near π), 'matched' for every other system (two quarter legs "
        "from both turning points: any time-reversible L, asymmetric wells included)",
    )
    s.add_argument(
        "--reference",
        default="auto",
        choices=("auto", "exact", "quadrature", "none"),
        help="what to compare with: a built-in's exact period, the quadrature oracle "
        "lagrax.quadrature_period (natural 1-DOF systems), or nothing (default auto: "
        "exact where known, else none)",
    )
    s.add_argument(
        "--chunk-size",
        type=int,
        default=128,
        help="lanes per compiled batch and device (default 128: on 2048 pendulum "
        "amplitudes, where step counts climb steeply towards π, 256 left only 83%% of "
        "the executed lane-steps useful, 128 gives 90%%)",
    )
    s.add_argument(
        "--devices",
        type=int,
        default=None,
        help="JAX devices per process: on a CPU, how many host devices to make of "
        f"it (default: every core, {_cpu_count()} here); on GPUs/TPUs, the first N",
    )
    s.add_argument(
        "--out", default=None, help="write every amplitude to a .csv or .npz file"
    )
    s.add_argument("--plot", default=None, help="write a chart (.png, .pdf, .svg)")
    s.add_argument("--rows", type=int, default=7, help="table rows per system")
    s.add_argument("--quiet", action="store_true", help="no progress bar on stderr")
    d = s.add_argument_group(
        "several processes (jax.distributed)",
        "Every process runs the same command; process 0 prints and writes the files. "
        "Where JAX detects the cluster (SLURM, Open MPI, Kubernetes, cloud TPU), "
        "--distributed alone is enough.",
    )
    d.add_argument(
        "--distributed",
        action="store_true",
        help="share the sweep with the other processes via jax.distributed",
    )
    d.add_argument("--coordinator", default=None, metavar="HOST:PORT")
    d.add_argument("--num-processes", type=int, default=None, metavar="N")
    d.add_argument("--process-id", type=int, default=None, metavar="I")
    d.add_argument(
        "--timeout",
        type=float,
        default=120.0,
        metavar="SECONDS",
        help="how long to wait for the other processes to join, and for a silent one "
        "before declaring it dead and exiting with an error (default 120)",
    )
    return p


# ------------------------------------------------------------------------------
# Arguments that need no JAX


def _check_writable(path, what, suffixes):
    ext = os.path.splitext(path)[1].lower()
    if ext not in suffixes:
        raise _UsageError(f"{what} must end in {' or '.join(suffixes)}; got {path!r}")
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise _UsageError(f"cannot write {what} {path!r}: no directory {directory!r}")
    if os.path.isdir(path):
        raise _UsageError(f"cannot write {what} {path!r}: it is a directory")
    try:
        with tempfile.NamedTemporaryFile(dir=directory, prefix=".lagrax-probe-"):
            pass
    except OSError as e:
        raise _UsageError(f"cannot write {what} {path!r}: {e.strerror}") from None


def _parse_params(items):
    params = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name.isidentifier():
            raise _UsageError(f"--param must be NAME=VALUE; got {item!r}")
        try:
            value = ast.literal_eval(text.strip())
        except (ValueError, SyntaxError):
            raise _UsageError(
                f"--param {item}: the value must be a number (or a Python literal "
                "such as a tuple)"
            ) from None
        if isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        elif isinstance(value, tuple | list):
            import numpy as np

            try:
                value = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                raise _UsageError(
                    f"--param {item}: a sequence value must hold numbers"
                ) from None
        params[name] = value
    return params


def _validate(args):
    """Checks that need neither JAX nor the target; `_UsageError` on failure."""
    if args.command is None:
        raise _UsageError(
            "expected a command: `lagrax sweep [TARGET]` or `lagrax systems`"
        )
    if args.command != "sweep":
        return
    if args.count < 1:
        raise _UsageError(f"--count must be a positive integer; got {args.count}")
    if args.chunk_size < 1:
        raise _UsageError(f"--chunk-size must be positive; got {args.chunk_size}")
    if args.rows < 0:
        raise _UsageError(f"--rows must be >= 0; got {args.rows}")
    if args.max_steps is not None and args.max_steps < 1:
        raise _UsageError(f"--max-steps must be positive; got {args.max_steps}")
    if args.devices is not None and args.devices < 1:
        raise _UsageError(f"--devices must be positive; got {args.devices}")
    for name in ("rtol", "atol"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise _UsageError(f"--{name} must be a positive number; got {value}")
    for name, value in (("--min", args.amin), ("--max", args.amax)):
        if value is not None and not math.isfinite(value):
            raise _UsageError(f"{name} must be a finite number; got {value}")
    if args.amin is not None and args.amax is not None and args.amin > args.amax:
        raise _UsageError(
            f"--min must not exceed --max; got --min {args.amin} --max {args.amax}"
        )
    args.params = _parse_params(args.param)
    targets = []
    for t in args.targets:
        targets.extend(["pendulum", "cycloid"] if t == "both" else [t])
    if len(set(targets)) != len(targets):
        raise _UsageError(f"a TARGET is given twice: {' '.join(args.targets)}")
    args.targets = targets
    launch = (args.coordinator, args.num_processes, args.process_id)
    if any(x is not None for x in launch):
        if any(x is None for x in launch):
            raise _UsageError(
                "--coordinator, --num-processes and --process-id go together "
                "(or give none of them where JAX detects the cluster)"
            )
        host, sep, port = args.coordinator.rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise _UsageError(
                f"--coordinator must be HOST:PORT; got {args.coordinator!r}"
            )
        if args.num_processes < 1:
            raise _UsageError(
                f"--num-processes must be positive; got {args.num_processes}"
            )
        if not 0 <= args.process_id < args.num_processes:
            raise _UsageError(
                f"--process-id must be in 0..{args.num_processes - 1}; got "
                f"{args.process_id}"
            )
        args.distributed = True
    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise _UsageError(f"--timeout must be a positive number; got {args.timeout}")
    if not args.distributed:
        _check_paths(args)


def _check_paths(args):
    if args.out is not None:
        _check_writable(args.out, "--out", (".csv", ".npz"))
    if args.plot is not None:
        _check_writable(args.plot, "--plot", (".png", ".pdf", ".svg"))


# ------------------------------------------------------------------------------
# JAX set-up: float64, devices, processes


class _Unreachable(Exception):
    """The other processes of a distributed run could not be reached (exit 3)."""


def _setup_jax(args):
    """Configures JAX before its backends start. Returns the devices to sweep over."""
    import jax

    jax.config.update("jax_enable_x64", True)
    # Compiling the sweep takes seconds; keep it across runs of the command.
    cache = os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")),
        "lagrax",
        "jax",
    )
    try:
        os.makedirs(cache, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    except Exception:  # a read-only home: just compile every time
        pass
    wanted = args.devices if args.devices is not None else _cpu_count()
    try:
        # Every core a host device: a CPU device runs one chunk at a time, so one
        # device is one core. Ignored where the default backend is a GPU or TPU.
        # Called from Python (`main(argv)`), JAX's device count is the caller's
        # unless --devices says otherwise.
        if args.devices is not None or args.from_command_line:
            jax.config.update("jax_num_cpu_devices", wanted)
    except RuntimeError:
        # JAX already started in this process (the command called from Python): keep
        # its devices, unless more were asked for than it has.
        if args.devices is not None and args.devices > len(jax.local_devices()):
            raise _UsageError(
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
            raise _UsageError(
                f"--distributed: {_first_line(e)} (JAX found no cluster to join: give "
                "--coordinator HOST:PORT --num-processes N --process-id I)"
            ) from None
        except Exception as e:  # noqa: BLE001 - the runtime's own error types
            raise _Unreachable(
                f"could not join the other processes at {args.coordinator or 'the'} "
                f"coordinator within {timeout} s: {_first_line(e)}"
            ) from None
        # gloo announces its first connection on stdout, where the table goes: make
        # that connection now, with stdout sent to stderr.
        sys.stdout.flush()
        saved = os.dup(1)
        try:
            os.dup2(2, 1)
            _broadcast(0)
        finally:
            os.dup2(saved, 1)
            os.close(saved)
        return jax.devices()
    devices = jax.local_devices()
    if args.devices is not None:
        devices = devices[: args.devices]
    return devices


def _first_line(e):
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}".rstrip(": ")


def _broadcast(value):
    """Process 0's int64 array on every process (JAX's collectives, nothing else)."""
    import jax
    import numpy as np

    if jax.process_count() == 1:
        return np.asarray(value)
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.broadcast_one_to_all(np.asarray(value)))


# ------------------------------------------------------------------------------
# Targets: built-in systems and your own Lagrangians


@dataclass
class _Target:
    name: str  # as given on the command line
    L: object  # kept for the whole run: sweep_periods caches its compiled code on it
    amplitude_label: str
    to_q0: object = None  # amplitude -> release point (None: the identity)
    exact: object = None  # amplitude -> exact period, or None
    T0: float | None = None
    default_range: tuple | None = None
    bounds: tuple | None = None  # (lo, hi) with lo < amplitude <= hi, or None
    method: str = "matched"
    coordinate: str = "q"
    extra: dict = field(default_factory=dict)


def _builtin_names():
    import pkgutil

    from .. import systems

    return sorted(
        m.name for m in pkgutil.iter_modules(systems.__path__) if m.name[0] != "_"
    )


def _builtin_module(name):
    return importlib.import_module(f"lagrax.systems.{name}")


def _exact_period_fn(module, name):
    """`period` (the uniform layout) or `<name>_period` (the older one), or None."""
    for attr in ("period", f"{name}_period"):
        fn = getattr(module, attr, None)
        if callable(fn):
            return fn
    return None


def _keywords_of(fn):
    """{name: default or inspect.Parameter.empty} of the keywords `fn` accepts, and
    whether it takes **kwargs."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return {}, True
    kws = {}
    var = False
    for p in sig.parameters.values():
        if p.kind is p.VAR_KEYWORD:
            var = True
        elif p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD):
            kws[p.name] = p.default
    return kws, var


def _call_with(fn, params, *args):
    """`fn(*args, **params)` with only the parameters `fn` accepts (for references)."""
    kws, var = _keywords_of(fn)
    if not var:
        params = {k: v for k, v in params.items() if k in kws}
    return fn(*args, **params)


def _call_factory(factory, params, what):
    kws, var = _keywords_of(factory)
    unknown = [k for k in params if k not in kws and not var]
    if unknown:
        have = ", ".join(kws) or "none"
        raise _UsageError(
            f"{what} has no parameter {unknown[0]!r} (its parameters: {have})"
        )
    missing = [
        k for k, d in kws.items() if d is inspect.Parameter.empty and k not in params
    ]
    if missing:
        raise _UsageError(
            f"{what} needs the parameter {missing[0]!r}"
            + (
                " (not a number: write a module that builds the Lagrangian and "
                "sweep it as module:attr)"
                if missing[0] == "potential"
                else " (give it with --param NAME=VALUE)"
            )
        )
    try:
        return factory(**params)
    except Exception as e:  # noqa: BLE001 - the user's code
        args = ", ".join(f"{k}={v!r}" for k, v in params.items())
        raise _UsageError(
            f"{what}: {getattr(factory, '__name__', 'factory')}({args}) raised "
            f"{_first_line(e)}"
        ) from None


def _builtin(name, params):
    import jax.numpy as jnp
    import numpy as np

    module = _builtin_module(name)
    what = f"system {name!r}"
    if name == "cycloid":
        # Integrated in u = cos(θ/2) = sin(a/2), regular at the cusp; the seed's θ
        # form has a mass that vanishes there.
        factory = getattr(module, "lagrangian_u", module.lagrangian)
        L = _call_factory(factory, params, what)
        exact_fn = _exact_period_fn(module, name)
        target = _Target(
            name,
            L,
            "a = π − θ₀ (rad)",
            to_q0=lambda a: np.sin(a / 2),
            default_range=(1e-3, math.pi),
            bounds=(0.0, math.pi),
            method="quarter",
            coordinate="u = sin(a/2)",
        )
    else:
        L = _call_factory(module.lagrangian, params, what)
        exact_fn = _exact_period_fn(module, name)
        target = _Target(name, L, "q₀")
        if name == "pendulum":
            target.amplitude_label = "θ₀ (rad)"
            target.default_range = (1e-3, math.pi - 1e-3)
            target.bounds = (0.0, math.pi)
            target.method = "quarter"
            target.coordinate = "θ"
        elif name == "asymmetric_well":
            k, a = float(params.get("k", 1.0)), float(params.get("a", 1.0))
            if k > 0 and a > 0:
                # The far turning point meets the barrier's height at x0 = k/(2a).
                target.default_range = (1e-3 * k / a, 0.49 * k / a)
            target.amplitude_label = "x₀"
    if exact_fn is not None:
        target.exact = lambda amp, fn=exact_fn: (
            np.asarray(_call_with(fn, params, jnp.asarray(amp)), dtype=np.float64)
            * np.ones_like(amp)
        )
    small = getattr(module, "small_amplitude_period", None)
    try:
        if callable(small):
            target.T0 = float(_call_with(small, params))
        elif target.exact is not None:
            T0 = float(target.exact(np.zeros(1))[0])
            target.T0 = T0 if math.isfinite(T0) and T0 > 0 else None
    except Exception:  # noqa: BLE001 - a reference that cannot say: no T0
        target.T0 = None
    return target


def _load_object(spec):
    """`module:attr` or `path/to/file.py:attr` -> (object, description)."""
    where, _, attr = spec.rpartition(":")
    if not where or not attr:
        raise _UsageError(
            f"TARGET {spec!r}: expected module:attr or path/to/file.py:attr"
        )
    if where.endswith(".py") or os.sep in where or "/" in where:
        path = os.path.abspath(where)
        if not os.path.isfile(path):
            raise _UsageError(f"TARGET {spec!r}: no such file {where!r}")
        name = "_lagrax_target_" + re.sub(r"\W", "_", path)
        loader = importlib.util.spec_from_file_location(name, path)
        if loader is None:
            raise _UsageError(f"TARGET {spec!r}: cannot import {where!r} (not Python)")
        module = importlib.util.module_from_spec(loader)
        sys.modules[name] = module
        try:
            loader.loader.exec_module(module)
        except Exception as e:  # noqa: BLE001 - the user's code
            del sys.modules[name]
            raise _UsageError(
                f"TARGET {spec!r}: importing {where!r} raised {_first_line(e)}"
            ) from None
    else:
        # As uvicorn does: modules in the working directory are importable.
        if os.getcwd() not in sys.path and "" not in sys.path:
            sys.path.insert(0, os.getcwd())
        try:
            module = importlib.import_module(where)
        except ModuleNotFoundError as e:
            if e.name is not None and where.startswith(e.name):
                raise _UsageError(
                    f"TARGET {spec!r}: no module named {e.name!r}"
                ) from None
            raise _UsageError(
                f"TARGET {spec!r}: importing {where!r} raised {_first_line(e)}"
            ) from None
        except Exception as e:  # noqa: BLE001 - the user's code
            raise _UsageError(
                f"TARGET {spec!r}: importing {where!r} raised {_first_line(e)}"
            ) from None
    obj = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise _UsageError(f"TARGET {spec!r}: {where!r} has no attribute {part!r}")
        obj = getattr(obj, part)
    return obj


def _positional_arity(fn):
    """(required positional parameters, whether *args), or None if unknowable."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return None
    required = [
        p
        for p in sig.parameters.values()
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
        and p.default is p.empty
    ]
    star = any(p.kind is p.VAR_POSITIONAL for p in sig.parameters.values())
    return len(required), star


def _user(spec, params):
    obj = _load_object(spec)
    if not callable(obj):
        raise _UsageError(
            f"TARGET {spec!r} is not callable (a {type(obj).__name__}): name a "
            "Lagrangian L(q, qdot, t) or a factory returning one"
        )
    arity = _positional_arity(obj)
    if arity is None or arity[0] == 3 or (arity[1] and arity[0] <= 3):
        if params:
            raise _UsageError(
                f"TARGET {spec!r} is a Lagrangian L(q, qdot, t), not a factory: "
                "--param does not apply"
            )
        L = obj
    elif arity[0] == 0:
        L = _call_factory(obj, params, f"factory {spec!r}")
        if not callable(L):
            raise _UsageError(
                f"factory {spec!r} returned a {type(L).__name__}, not a Lagrangian "
                "L(q, qdot, t)"
            )
        arity = _positional_arity(L)
        if arity is not None and not (arity[0] == 3 or (arity[1] and arity[0] <= 3)):
            raise _UsageError(
                f"factory {spec!r} returned a function of {arity[0]} required "
                "argument(s), not a Lagrangian L(q, qdot, t)"
            )
    else:
        raise _UsageError(
            f"TARGET {spec!r} takes {arity[0]} required argument(s): expected a "
            "Lagrangian L(q, qdot, t) or a factory f(**params) returning one"
        )
    return _Target(spec, L, "q₀")


def _coordinates(L):
    """How many coordinates `L(q, qdot, t)` uses, or a `_UsageError` saying why not.

    JAX clamps out-of-range static indices, so a two-coordinate L written with `q[1]`
    also runs on q of shape (1,): count the coordinates L actually depends on, at a
    generic point of the widest shape it accepts.
    """
    import jax
    import jax.numpy as jnp

    def shape_with(n):
        q = jax.ShapeDtypeStruct((n,), jnp.float64)
        t = jax.ShapeDtypeStruct((), jnp.float64)
        return jax.eval_shape(L, q, q, t)

    accepted, first_error = [], None
    for n in range(1, _PROBE_DOF + 1):
        try:
            out = shape_with(n)
        except Exception as e:  # noqa: BLE001 - the user's code
            first_error = first_error or e
            continue
        shape = getattr(out, "shape", None)
        if shape != ():
            raise _UsageError(
                "L(q, qdot, t) must return a scalar; got "
                + (f"shape {shape}" if shape is not None else type(out).__name__)
            )
        accepted.append(n)
    if not accepted:
        raise _UsageError(
            "L(q, qdot, t) with q, qdot of shape (1,) and t a scalar raised "
            f"{_first_line(first_error)}"
        )
    n = max(accepted)
    q = 0.3 + 0.11 * jnp.arange(n, dtype=jnp.float64)
    qdot = 0.2 + 0.07 * jnp.arange(n, dtype=jnp.float64)
    try:
        gq, gv = jax.grad(lambda q, v: L(q, v, 0.1), argnums=(0, 1))(q, qdot)
        used = [i for i in range(n) if gq[i] != 0 or gv[i] != 0]
    except Exception:  # noqa: BLE001 - not differentiable here: trust the shapes
        used = []
    return max(len(used) and used[-1] + 1, min(accepted))


def _check_one_dof(target):
    """`L(q, qdot, t)` must be a Lagrangian of one coordinate."""
    what = f"TARGET {target.name!r}" if ":" in target.name else target.name
    try:
        n = _coordinates(target.L)
    except _UsageError as e:
        raise _UsageError(
            f"{what}: {e}; lagrax sweep needs a Lagrangian of one coordinate"
        ) from None
    if n != 1:
        raise _UsageError(
            f"{what} has {n} coordinates (q of shape ({n},)); lagrax sweep needs a "
            "Lagrangian of one coordinate"
        )


def _targets(args):
    builtins = set(_builtin_names())
    out = []
    for name in args.targets:
        if ":" in name:
            target = _user(name, args.params)
        elif name in builtins:
            target = _builtin(name, args.params)
        else:
            raise _UsageError(
                f"unknown system {name!r}: a built-in ({', '.join(sorted(builtins))}; "
                "see `lagrax systems`) or your own as module:attr or file.py:attr"
            )
        _check_one_dof(target)
        target.method = args.method or target.method
        if target.default_range is None and (args.amin is None or args.amax is None):
            raise _UsageError(
                f"{name}: give the amplitudes with --min and --max (release points "
                f"{target.amplitude_label})"
            )
        lo = target.default_range[0] if args.amin is None else args.amin
        hi = target.default_range[1] if args.amax is None else args.amax
        if lo > hi:
            raise _UsageError(
                f"--min must not exceed --max; got --min {lo} --max {hi} for {name}"
            )
        if target.bounds is not None:
            b0, b1 = target.bounds
            if not (b0 < lo <= hi <= b1):
                raise _UsageError(
                    f"amplitudes must satisfy 0 < --min <= --max <= π (rad); got "
                    f"--min {lo} --max {hi} for the {name}"
                )
        target.extra["range"] = (lo, hi)
        reference = args.reference
        if reference == "auto":
            reference = "exact" if target.exact is not None else "none"
        if reference == "exact" and target.exact is None:
            raise _UsageError(
                f"{name} has no exact period: use --reference quadrature (natural "
                "systems) or --reference none"
            )
        target.extra["reference"] = reference
        out.append(target)
    return out


# ------------------------------------------------------------------------------
# The sweep, in checkpointed blocks


def _atomic_write(path, write):
    """`write(tmp_path)`, then rename over `path`: never a half-written file."""
    directory = os.path.dirname(os.path.abspath(path))
    suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=".lagrax-", suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _safe(name):
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


class _Blocks:
    """Where each block of amplitudes stands: computed here, or resumed from disk.

    Only process 0 touches the checkpoint directory; it tells the others which blocks
    are done (a broadcast), so that every process skips the same ones.
    """

    def __init__(self, args, targets, devices):
        import jax
        import numpy as np

        self.writer = jax.process_index() == 0
        # A sweep smaller than one chunk per device would mostly run padding.
        self.chunk_size = min(args.chunk_size, -(-args.count // len(devices)))
        self.block = self.chunk_size * len(devices) * _BLOCK_CHUNKS
        self.n_blocks = {t.name: -(-args.count // self.block) for t in targets}
        self.dir = None if args.out is None else args.out + ".partial"
        done = []
        if self.dir is not None and self.writer:
            self._prepare(args, targets, devices)
        for t in targets:
            for b in range(self.n_blocks[t.name]):
                done.append(self.dir is not None and self.writer and self.exists(t, b))
        self.done = _broadcast(np.array(done, dtype=np.int64)).astype(bool)
        self.resumed = int(self.done.sum())

    def _prepare(self, args, targets, devices):
        import shutil

        # Keyed by everything that changes the numbers: a rerun of the same command
        # resumes; a different one restarts.
        manifest = {
            k: getattr(args, k)
            for k in ("count", "solver", "rtol", "atol", "max_steps")
        }
        manifest["chunk_size"] = self.chunk_size
        manifest["devices"] = len(devices)
        manifest["targets"] = {
            t.name: [list(t.extra["range"]), t.method] for t in targets
        }
        manifest["params"] = args.params
        manifest_path = os.path.join(self.dir, "manifest.json")
        if os.path.isdir(self.dir):
            try:
                with open(manifest_path) as f:
                    same = json.load(f) == json.loads(json.dumps(manifest))
            except (OSError, ValueError):
                same = False
            if not same:
                shutil.rmtree(self.dir)
        if not os.path.isdir(self.dir):
            os.makedirs(self.dir)

            def write(p):
                with open(p, "w") as f:
                    json.dump(manifest, f)

            _atomic_write(manifest_path, write)

    def path(self, target, b):
        return os.path.join(self.dir, f"{_safe(target.name)}-{b:05d}.npz")

    def exists(self, target, b):
        return os.path.exists(self.path(target, b))

    def is_done(self, targets, target, b):
        index = 0
        for t in targets:
            if t is target:
                return bool(self.done[index + b])
            index += self.n_blocks[t.name]
        raise KeyError(target.name)


def _sweep(target, args, devices, blocks, targets, bar):
    import diffrax as dfx
    import jax.numpy as jnp
    import numpy as np

    import lagrax

    solver = {
        "auto": lambda: lagrax.Taylor(fallback=dfx.Dopri8()),
        "dopri8": dfx.Dopri8,
        "dopri5": dfx.Dopri5,
        "tsit5": dfx.Tsit5,
        "taylor": lagrax.Taylor,
    }[args.solver]()
    lo, hi = target.extra["range"]
    amplitude = np.linspace(lo, hi, args.count)
    q0 = amplitude if target.to_q0 is None else target.to_q0(amplitude)
    q0 = np.asarray(q0, dtype=np.float64)
    kwargs = {} if args.max_steps is None else {"max_steps": args.max_steps}
    parts = []
    stepped = None  # the solver that ran (the default resolves per L)
    start = time.perf_counter()
    for b in range(blocks.n_blocks[target.name]):
        sl = slice(b * blocks.block, min((b + 1) * blocks.block, args.count))
        if blocks.is_done(targets, target, b):
            part = None
            if blocks.writer:
                with np.load(blocks.path(target, b)) as f:
                    part = {k: f[k] for k in f.files}
        else:

            def progress(done, total, offset=sl.start):
                bar.to(offset + done)

            res = lagrax.sweep_periods(
                target.L,
                jnp.asarray(q0[sl]),
                solver=solver,
                rtol=args.rtol,
                atol=args.atol,
                method=target.method,
                chunk_size=blocks.chunk_size,
                devices=devices,
                progress=progress if bar.active else None,
                **kwargs,
            )
            stepped = res.solver
            part = {
                "period": np.asarray(res.periods),
                "status": np.asarray(res.status),
                "steps": np.asarray(res.num_steps),
                "useful_fraction": np.asarray(res.useful_fraction),
            }
            if hasattr(res, "error_estimate"):
                part["error_estimate"] = np.asarray(res.error_estimate)
            if blocks.dir is not None and blocks.writer:
                _atomic_write(
                    blocks.path(target, b), lambda p, part=part: np.savez(p, **part)
                )
        parts.append(part)
        bar.to(sl.stop)
    elapsed = time.perf_counter() - start
    if not blocks.writer:
        return None
    r = {
        "system": target.name,
        "amplitude": amplitude,
        "q0": q0,
        "seconds": elapsed,
        "target": target,
        "solver": None if stepped is None else type(stepped).__name__,
    }
    for key in ("period", "status", "steps"):
        r[key] = np.concatenate([p[key] for p in parts])
    if all("error_estimate" in p for p in parts):
        r["error_estimate"] = np.concatenate([p["error_estimate"] for p in parts])
    # useful fraction of the whole sweep from the blocks' own (useful = Σ steps).
    useful = np.array([p["steps"].sum() for p in parts], dtype=float)
    fraction = np.array([float(p["useful_fraction"]) for p in parts])
    executed = np.where(fraction > 0, useful / np.maximum(fraction, 1e-300), 0.0)
    r["useful_fraction"] = useful.sum() / max(executed.sum(), 1.0)
    _add_reference(r, target, args)
    return r


def _add_reference(r, target, args):
    import jax.numpy as jnp
    import numpy as np

    import lagrax

    kind = target.extra["reference"]
    n = len(r["amplitude"])
    ref = np.full(n, np.nan)
    if kind == "exact":
        ref = target.exact(r["amplitude"])
    elif kind == "quadrature":
        q0 = r["q0"]
        pieces = []
        for s in range(0, n, _QUADRATURE_BLOCK):
            piece = q0[s : s + _QUADRATURE_BLOCK]
            # Padded to one shape: one compilation for every block.
            padded = np.concatenate(
                [piece, np.full(min(n, _QUADRATURE_BLOCK) - len(piece), piece[-1])]
            )
            res = lagrax.quadrature_period(target.L, jnp.asarray(padded), throw=False)
            periods = np.where(
                np.asarray(res.status) == 0, np.asarray(res.periods), np.nan
            )
            pieces.append(periods[: len(piece)])
        ref = np.concatenate(pieces)
    r["reference"] = np.asarray(ref, dtype=np.float64)
    r["reference_kind"] = kind
    with np.errstate(invalid="ignore", divide="ignore"):
        r["rel_error"] = np.abs(r["period"] / r["reference"] - 1)
        r["T_over_T0"] = r["period"] / (target.T0 if target.T0 else np.nan)


# ------------------------------------------------------------------------------
# Output: table, files, chart


def _status_name(code):
    import lagrax

    names = getattr(lagrax, "STATUS_CODES", None)
    if isinstance(names, dict) and code in names:
        name = names[code]
        return name if isinstance(name, str) else str(name[0])
    return "success" if code == 0 else f"status_{code}"


_REFERENCE_WORDS = {
    "exact": "the exact period",
    "quadrature": "lagrax.quadrature_period",
    "none": "no reference",
}


def _table(results, rows):
    import numpy as np

    estimates = any("error_estimate" in r for r in results)
    normalized = any(r["target"].T0 for r in results)
    width = max(9, *(len(r["system"]) for r in results))
    head = (
        f"{'system':<{width}} {'amplitude':>10} {'period':>18} "
        + (f"{'T/T0':>12} " if normalized else "")
        + f"{'reference':>18} {'rel. error':>10}"
    )
    if estimates:
        head += f" {'estimate':>9}"
    lines = [head + "  status"]
    for r in results:
        n = len(r["amplitude"])
        picks = sorted(set(np.linspace(0, n - 1, min(rows, n)).round().astype(int)))
        for i in picks:
            code = int(r["status"][i])
            line = (
                f"{r['system']:<{width}} {r['amplitude'][i]:>10.6f} "
                f"{r['period'][i]:>18.15f} "
                + (f"{r['T_over_T0'][i]:>12.9f} " if normalized else "")
                + f"{r['reference'][i]:>18.15f} {r['rel_error'][i]:>10.1e}"
            )
            if estimates:
                est = r.get("error_estimate", np.full(n, np.nan))[i]
                line += f" {est:>9.1e}"
            lines.append(line + f"  {_status_name(code)}")
    lines.append("")
    for r in results:
        ok = r["status"] == 0
        kind = r["reference_kind"]
        if kind == "none":
            accuracy = "no reference (--reference quadrature compares)"
        else:
            compared = ok & np.isfinite(r["rel_error"])
            worst = float(np.max(r["rel_error"][compared])) if compared.any() else None
            accuracy = "max relative error " + (
                f"{worst:.1e}" if worst is not None else "n/a"
            )
            accuracy += f" vs {_REFERENCE_WORDS[kind]}"
            missing = int((ok & ~np.isfinite(r["reference"])).sum())
            if missing:
                accuracy += f" ({missing} without a reference value)"
        if "error_estimate" in r and ok.any():
            accuracy += f", max error estimate {np.nanmax(r['error_estimate'][ok]):.1e}"
        lines.append(
            f"{r['system']}: {len(ok)} amplitudes"
            + (f" ({r['solver']})" if r.get("solver") else "")
            + f", {int((~ok).sum())} failed, "
            f"{accuracy}, {r['seconds']:.2f} s (compile included), useful lane-steps "
            f"{r['useful_fraction']:.0%}"
        )
    return "\n".join(lines)


_COLUMNS = ("amplitude", "q0", "period", "T_over_T0", "reference", "rel_error")


def _write_out(path, results):
    import csv

    import numpy as np

    estimates = all("error_estimate" in r for r in results)
    columns = (*_COLUMNS, "error_estimate") if estimates else _COLUMNS
    if path.lower().endswith(".npz"):
        data = {
            "system": np.concatenate(
                [np.full(len(r["amplitude"]), r["system"]) for r in results]
            ),
            "reference_kind": np.concatenate(
                [np.full(len(r["amplitude"]), r["reference_kind"]) for r in results]
            ),
        }
        for c in (*columns, "status", "steps"):
            data[c] = np.concatenate([r[c] for r in results])
        _atomic_write(path, lambda p: np.savez(p, **data))
        return

    def write(p):
        with open(p, "w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(
                ["system", *columns, "status", "status_name", "steps", "reference_kind"]
            )
            for r in results:
                for i in range(len(r["amplitude"])):
                    code = int(r["status"][i])
                    w.writerow(
                        [
                            r["system"],
                            *(repr(float(r[c][i])) for c in columns),
                            code,
                            _status_name(code),
                            int(r["steps"][i]),
                            r["reference_kind"],
                        ]
                    )

    _atomic_write(path, write)


def _label(r):
    t = r["target"]
    descriptions = {
        "pendulum": "simple pendulum",
        "cycloid": "cycloidal pendulum",
    }
    return f"{descriptions.get(t.name, t.name)} (amplitude {t.amplitude_label})"


def _chart(results, rtol):
    """The figure: T/T₀ (or T) against amplitude, and the relative error below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib import ticker

    fig, (top, bottom) = plt.subplots(
        2,
        1,
        figsize=(7.0, 6.4),
        sharex=True,
        gridspec_kw={"height_ratios": [3, 2]},
    )
    normalized = all(r["target"].T0 for r in results)
    floor = 1e-17
    any_failed = False
    for k, r in enumerate(results):
        color = f"C{k}"
        ok = r["status"] == 0
        y = r["T_over_T0"] if normalized else r["period"]
        top.plot(r["amplitude"][ok], y[ok], color=color, label=_label(r))
        if (~ok).any():
            any_failed = True
            for ax in (top, bottom):
                ax.plot(
                    r["amplitude"][~ok],
                    np.full(int((~ok).sum()), 0.03),
                    "x",
                    color=color,
                    markersize=5,
                    transform=ax.get_xaxis_transform(),
                    label=f"failed: {int((~ok).sum())} ({r['system']})"
                    if ax is top
                    else None,
                )
        kind = r["reference_kind"]
        if kind != "none":
            err = r["rel_error"]
            shown = ok & np.isfinite(err)
            bottom.plot(
                r["amplitude"][shown],
                np.maximum(err[shown], floor),
                ".",
                color=color,
                markersize=2.5,
                label=f"{r['system']}: |T / T_ref − 1|, T_ref = {kind}",
            )
        if "error_estimate" in r:
            est = r["error_estimate"]
            shown = ok & np.isfinite(est)
            bottom.plot(
                r["amplitude"][shown],
                np.maximum(est[shown], floor),
                "-",
                color=color,
                alpha=0.6,
                linewidth=1,
                label=f"{r['system']}: error estimate",
            )
    bottom.axhline(
        rtol, color="0.4", linestyle=":", linewidth=1, label=f"rtol {rtol:g}"
    )
    top.set_ylabel("T / T₀" if normalized else "period T")
    ys = [
        (r["T_over_T0"] if normalized else r["period"])[r["status"] == 0]
        for r in results
    ]
    ys = np.concatenate(ys) if ys else np.array([])
    ys = ys[np.isfinite(ys) & (ys > 0)]
    if ys.size and ys.max() / ys.min() > 30:
        top.set_yscale("log")
        # Plain numbers on every decade and between them, never "6×10⁰".
        top.yaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        top.yaxis.set_minor_formatter(ticker.NullFormatter())
    else:
        top.yaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
    top.set_title("Period against amplitude (lagrax sweep)")
    top.grid(True, which="both", alpha=0.3)
    top.legend(fontsize=8)
    bottom.set_yscale("log")
    shown = [
        line.get_ydata() for line in bottom.get_lines() if len(line.get_ydata()) > 1
    ]
    shown = np.concatenate(shown) if shown else np.array([rtol])
    bottom.set_ylim(max(floor / 2, shown.min() / 4), max(rtol, shown.max()) * 8)
    bottom.yaxis.set_major_locator(ticker.LogLocator(numticks=8))
    bottom.set_ylabel("relative error")
    bottom.set_xlabel("amplitude")
    bottom.grid(True, which="major", alpha=0.3)
    if bottom.get_legend_handles_labels()[0]:
        bottom.legend(fontsize=7, loc="upper left")
    note = f"errors below {floor:.0e} drawn at it"
    if any_failed:
        note += "; × marks failed amplitudes"
    bottom.set_title(note, fontsize=8, loc="right")
    fig.tight_layout()
    return fig


def _plot(path, results, rtol):
    import matplotlib.pyplot as plt

    fig = _chart(results, rtol)
    ext = os.path.splitext(path)[1][1:]
    _atomic_write(path, lambda p: fig.savefig(p, format=ext, dpi=120))
    plt.close(fig)


class _Bar:
    """tqdm over one system's amplitudes: done, periods/s, time left. Silent when
    quiet, on processes other than 0, or when stderr is not a terminal."""

    def __init__(self, name, total, enabled):
        self.bar = None
        if enabled:
            from tqdm.auto import tqdm

            self.bar = tqdm(
                total=total,
                desc=name,
                unit=" periods",
                file=sys.stderr,
                disable=None,  # None: off when stderr is not a terminal
                dynamic_ncols=True,
                smoothing=0.1,
            )
            if self.bar.disable:
                self.bar = None

    @property
    def active(self):
        return self.bar is not None

    def to(self, n):
        if self.bar is not None and n > self.bar.n:
            self.bar.update(n - self.bar.n)

    def close(self):
        if self.bar is not None:
            self.bar.close()


def _run_sweep(args):
    import jax
    import numpy as np

    devices = _setup_jax(args)
    targets = _targets(args)
    writer = jax.process_index() == 0
    if args.distributed:
        # Only process 0 writes, so only its view of the paths counts; the others
        # learn the verdict and stop with it.
        error = None
        if writer:
            try:
                _check_paths(args)
            except _UsageError as e:
                error = e
        if int(_broadcast(np.int64(error is not None))):
            raise error or _UsageError("process 0 cannot write --out/--plot")
    blocks = _Blocks(args, targets, devices)
    if writer and blocks.resumed and not args.quiet:
        total = sum(blocks.n_blocks.values())
        print(
            f"lagrax: resuming from {blocks.dir}: {blocks.resumed} of {total} blocks "
            "already done",
            file=sys.stderr,
        )
    results = []
    for t in targets:
        bar = _Bar(t.name, args.count, writer and not args.quiet)
        try:
            results.append(_sweep(t, args, devices, blocks, targets, bar))
        finally:
            bar.close()
    failed = 0
    if writer:
        print(_table(results, args.rows))
        if args.out is not None:
            import shutil

            _write_out(args.out, results)
            shutil.rmtree(blocks.dir, ignore_errors=True)
            print(f"wrote {args.out}")
        if args.plot is not None:
            _plot(args.plot, results, args.rtol)
            print(f"wrote {args.plot}")
        failed = sum(int((r["status"] != 0).sum()) for r in results)
        if failed:
            codes, counts = np.unique(
                np.concatenate([r["status"][r["status"] != 0] for r in results]),
                return_counts=True,
            )
            import lagrax

            print(
                f"{failed} amplitudes failed: see the status column; "
                + "; ".join(
                    f"{n} × {_status_name(int(c))} ({lagrax.status_message(int(c))})"
                    for c, n in zip(codes, counts)
                ),
                file=sys.stderr,
            )
    # Every process leaves with process 0's verdict.
    failed = int(_broadcast(np.int64(failed)))
    return 1 if failed else 0


# ------------------------------------------------------------------------------
# lagrax systems


def _systems_lines():
    import numpy as np

    lines = []
    names = _builtin_names()
    width = max(len(n) for n in names)
    for name in names:
        module = _builtin_module(name)
        factory = getattr(module, "lagrangian", None)
        if not callable(factory):
            continue
        kws, _ = _keywords_of(factory)
        params = " ".join(
            f"{k}=<required>" if d is inspect.Parameter.empty else f"{k}={d!r}"
            for k, d in kws.items()
        )
        notes = []
        try:
            target = _builtin(name, {})
            _check_one_dof(target)
        except _UsageError as e:
            text = str(e)
            m = re.search(r"has (\d+) coordinates", text)
            if m:
                notes.append(f"{m.group(1)} coordinates: not for lagrax sweep")
            elif "needs the parameter" in text:
                notes.append("needs a function argument: sweep it as module:attr")
            else:
                notes.append(f"not for lagrax sweep: {text}")
        else:
            notes.append(
                "exact period"
                if target.exact is not None
                else "no exact period (--reference quadrature)"
            )
            if target.default_range is not None:
                lo, hi = target.default_range
                notes.append(
                    f"amplitude {target.amplitude_label} {lo:g}..{np.round(hi, 6):g}"
                )
            else:
                notes.append("needs --min/--max")
        lines.append(f"{name:<{width}}  {params}  [{'; '.join(notes)}]")
    return lines


# ------------------------------------------------------------------------------


def main(argv=None) -> int:
    """Entry point of the `lagrax` console script."""
    try:
        args = _parser().parse_args(argv)
        args.from_command_line = argv is None
        _validate(args)
        if args.command == "systems":
            import jax

            jax.config.update("jax_enable_x64", True)
            print("\n".join(_systems_lines()))
            return 0
        return _run_sweep(args)
    except _UsageError as e:
        print(f"lagrax: error: {e}", file=sys.stderr)
        return 2
    except _Unreachable as e:
        print(f"lagrax: error: {e}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print(
            "\nlagrax: interrupted; rerun the same command to resume", file=sys.stderr
        )
        return 130
