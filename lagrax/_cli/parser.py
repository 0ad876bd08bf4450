"""The command line's arguments, and the checks that need neither JAX nor a target."""

import argparse
import ast
import math
import os
import tempfile


SOLVERS = ("auto", "taylor", "dopri8", "dopri5", "tsit5")
DEFAULT_TARGETS = "both"  # the built-ins whose `SWEEP` says `default=True`


class UsageError(Exception):
    """Bad arguments or unusable files: one line on stderr, exit 2. `coordinates`:
    how many coordinates a Lagrangian has, where that is what is wrong."""

    def __init__(self, message: str, *, coordinates: int | None = None):
        super().__init__(message)
        self.coordinates = coordinates


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, no usage dump, exit 2
        raise UsageError(message)


def first_line(e):
    """`Type: first line of the message` of an exception raised by someone else."""
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}".rstrip(": ")


def cpu_count():
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def parser():
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
    c = sub.add_parser(
        "cache",
        help="show or empty the disk cache of compiled programs",
        description=(
            "The library's disk cache of compiled programs ($LAGRAX_CACHE_DIR, else "
            "~/.cache/lagrax/executables; LAGRAX_CACHE_DIR= turns it off). 'info': "
            "where it is, whether it is on, its size; 'clear': remove its entries."
        ),
    )
    c.add_argument("action", choices=("info", "clear"), help="info or clear")
    s = sub.add_parser(
        "sweep",
        help="periods of many amplitudes against a reference",
        description=(
            "Period against amplitude, float64. TARGET: a built-in system (`lagrax "
            f"systems` lists them; '{DEFAULT_TARGETS}', the default, sweeps those it "
            "marks 'default') or your own Lagrangian of one coordinate as module:attr "
            "or path/to/file.py:attr, naming L(q, qdot, t) or a factory returning one."
        ),
    )
    s.add_argument(
        "targets",
        nargs="*",
        default=[DEFAULT_TARGETS],
        metavar="TARGET",
        help=f"built-in name, module:attr or file.py:attr (default: {DEFAULT_TARGETS})",
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
        help="smallest amplitude (default: the built-in's range, `lagrax systems` "
        "lists it; your own L: the release point q0, required)",
    )
    s.add_argument(
        "--max",
        type=float,
        default=None,
        dest="amax",
        help="largest amplitude (default: the built-in's range; required for your "
        "own L)",
    )
    s.add_argument(
        "--solver",
        default="auto",
        choices=SOLVERS,
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
        help="how much of each orbit to integrate (see lagrax.sweep_periods). Default: "
        "the built-in's own ('quarter' for the mirror-symmetric ones, exact there and "
        "best conditioned near a hump), else 'matched' (two quarter legs from both "
        "turning points: any time-reversible L, asymmetric wells included)",
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
        "--lanes",
        type=int,
        default=None,
        help="lanes per compiled loop and device (default 256 on a CPU, as "
        "lagrax.sweep_periods: the command and the library share their compiled "
        "programs; on a GPU every amplitude of a device's share, up to 262144)",
    )
    s.add_argument(
        "--devices",
        type=int,
        default=None,
        help="JAX devices per process: on a CPU, how many host devices to make of "
        f"it (default: every core, {cpu_count()} here); on GPUs/TPUs, the first N",
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


def check_writable(path, what, suffixes):
    ext = os.path.splitext(path)[1].lower()
    if ext not in suffixes:
        raise UsageError(f"{what} must end in {' or '.join(suffixes)}; got {path!r}")
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise UsageError(f"cannot write {what} {path!r}: no directory {directory!r}")
    if os.path.isdir(path):
        raise UsageError(f"cannot write {what} {path!r}: it is a directory")
    try:
        with tempfile.NamedTemporaryFile(dir=directory, prefix=".lagrax-probe-"):
            pass
    except OSError as e:
        raise UsageError(f"cannot write {what} {path!r}: {e.strerror}") from None


def check_paths(args):
    if args.out is not None:
        check_writable(args.out, "--out", (".csv", ".npz"))
    if args.plot is not None:
        check_writable(args.plot, "--plot", (".png", ".pdf", ".svg"))


def _parse_params(items):
    params = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name.isidentifier():
            raise UsageError(f"--param must be NAME=VALUE; got {item!r}")
        try:
            value = ast.literal_eval(text.strip())
        except (ValueError, SyntaxError):
            raise UsageError(
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
                raise UsageError(
                    f"--param {item}: a sequence value must hold numbers"
                ) from None
        params[name] = value
    return params


def validate(args):
    """Checks that need neither JAX nor the target; `UsageError` on failure."""
    if args.command is None:
        raise UsageError(
            "expected a command: `lagrax sweep [TARGET]`, `lagrax systems` or "
            "`lagrax cache info|clear`"
        )
    if args.command != "sweep":
        return
    if args.count < 1:
        raise UsageError(f"--count must be a positive integer; got {args.count}")
    if args.lanes is not None and args.lanes < 1:
        raise UsageError(f"--lanes must be positive; got {args.lanes}")
    if args.rows < 0:
        raise UsageError(f"--rows must be >= 0; got {args.rows}")
    if args.max_steps is not None and args.max_steps < 1:
        raise UsageError(f"--max-steps must be positive; got {args.max_steps}")
    if args.devices is not None and args.devices < 1:
        raise UsageError(f"--devices must be positive; got {args.devices}")
    for name in ("rtol", "atol"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise UsageError(f"--{name} must be a positive number; got {value}")
    for name, value in (("--min", args.amin), ("--max", args.amax)):
        if value is not None and not math.isfinite(value):
            raise UsageError(f"{name} must be a finite number; got {value}")
    if args.amin is not None and args.amax is not None and args.amin > args.amax:
        raise UsageError(
            f"--min must not exceed --max; got --min {args.amin} --max {args.amax}"
        )
    args.params = _parse_params(args.param)
    if len(set(args.targets)) != len(args.targets):
        raise UsageError(f"a TARGET is given twice: {' '.join(args.targets)}")
    launch = (args.coordinator, args.num_processes, args.process_id)
    if any(x is not None for x in launch):
        if any(x is None for x in launch):
            raise UsageError(
                "--coordinator, --num-processes and --process-id go together "
                "(or give none of them where JAX detects the cluster)"
            )
        host, sep, port = args.coordinator.rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise UsageError(
                f"--coordinator must be HOST:PORT; got {args.coordinator!r}"
            )
        if args.num_processes < 1:
            raise UsageError(
                f"--num-processes must be positive; got {args.num_processes}"
            )
        if not 0 <= args.process_id < args.num_processes:
            raise UsageError(
                f"--process-id must be in 0..{args.num_processes - 1}; got "
                f"{args.process_id}"
            )
        args.distributed = True
    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise UsageError(f"--timeout must be a positive number; got {args.timeout}")
    if not args.distributed:
        check_paths(args)
