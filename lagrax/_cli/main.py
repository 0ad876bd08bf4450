r"""The `lagrax` command: `lagrax sweep [TARGET ...]`, `lagrax systems` and
`lagrax cache info|clear`.

`lagrax sweep` measures the period of many amplitudes at once with
`lagrax.sweep_periods` and compares it with a reference. TARGET is

- a built-in system of `lagrax.systems` (`lagrax systems` lists them, each with its
  amplitude and default range), compared with its exact period where it has one;
- or your own Lagrangian of one coordinate, `module:attr` or `path/to/file.py:attr`
  (the convention of uvicorn and gunicorn), naming `L(q, qdot, t)` or a factory that
  returns one (`--param name=value` is passed to the factory); the amplitude is then the
  release point $q_0$ and the reference is `lagrax.quadrature_period` on request.

The table and the `--out` file give $T/T_0$, with $T_0$ the small-amplitude period:
the system's own formula where it has one, else $2\pi/\omega$ at the bottom of the well
the first release point swings through ($\omega^2 = -\partial\ddot q/\partial q$
there); where there is no such stable point the column is left out (NaN for that
system where another one has it).

Parameters default to 1 (`g = r = R = 1`). Exit status: 0 all periods succeeded, 1 some
amplitudes failed (their status is in the table and file), 2 bad arguments or unusable
files, 3 the other processes of a `--distributed` run could not be reached, 130
interrupted (rerun the same command to resume from the checkpoints next to `--out`).

The modules: `parser` (arguments), `processes` (JAX, devices, other processes),
`targets` (what is swept), `checkpoint` (blocks on disk), `run` (the sweep),
`output` (table, files, progress) and `chart`.
"""

import functools
import sys
import warnings

from .parser import parser, UsageError, validate
from .processes import Unreachable
from .run import run_sweep
from .targets import systems_lines


def main(argv=None) -> int:
    """Entry point of the `lagrax` console script."""
    with warnings.catch_warnings():
        warnings.showwarning = functools.partial(_show_warning, warnings.showwarning)
        return _main(argv)


def _show_warning(default, message, category, filename, lineno, file=None, line=None):
    """The library's own notices ("lagrax: ...") as one line on stderr, without the
    file and line of the code that warned (a command's user did not write it)."""
    if str(message).startswith("lagrax:"):
        print(str(message), file=sys.stderr if file is None else file)
    else:
        default(message, category, filename, lineno, file, line)


def _main(argv) -> int:
    try:
        args = parser().parse_args(argv)
        args.from_command_line = argv is None
        validate(args)
        if args.command == "cache":
            return _cache(args.action)
        if args.command == "systems":
            import jax

            jax.config.update("jax_enable_x64", True)
            print("\n".join(systems_lines()))
            return 0
        return run_sweep(args)
    except UsageError as e:
        print(f"lagrax: error: {e}", file=sys.stderr)
        return 2
    except Unreachable as e:
        print(f"lagrax: error: {e}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print(
            "\nlagrax: interrupted; rerun the same command to resume", file=sys.stderr
        )
        return 130


def _cache(action) -> int:
    """`lagrax cache info|clear`: the disk cache's folder, state and size, or empty
    it (without starting JAX)."""
    from .._cache import folder

    if action == "clear":
        files, size = folder.clear()
        print(
            f"removed {files} files ({size / 2**20:.1f} MiB) from {folder.location()}"
        )
        return 0
    info = folder.info()
    print(f"folder   {info['folder'] or '(none)'}")
    print(f"state    {info['state']}")
    print(f"entries  {info['entries']} files, {info['bytes'] / 2**20:.1f} MiB")
    print(
        f"limit    {info['max_bytes'] / 2**20:.0f} MiB (least recently used go first)"
    )
    return 0
