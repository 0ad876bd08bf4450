r"""The `lagrax` command: `lagrax sweep [pendulum|cycloid|both]`.

Measures the period of many amplitudes at once with `lagrax.sweep_periods` and compares
it with the exact one:

- pendulum: amplitude $\theta_0$ (radians from the downward vertical), exact
  $T = 2\pi\sqrt{r/g}/\mathrm{AGM}(1, \cos(\theta_0/2))$, $T_0 = 2\pi\sqrt{r/g}$;
- cycloid (Huygens): amplitude $a = \pi - \theta_0$, the angle the generating circle
  has rolled from the bottom ($a = \pi$ is release at the cusp), integrated in the
  regular coordinate $u = \cos(\theta_0/2) = \sin(a/2)$; exact
  $T = T_0 = 4\pi\sqrt{R/g}$ for every amplitude.

Units: $g = r = R = 1$. Exit status: 0 all periods succeeded, 1 some amplitudes failed
(their status is in the table and file), 2 bad arguments, 130 interrupted (rerun the
same command to resume from the checkpoints next to `--out`).
"""

import argparse
import functools
import json
import math
import os
import sys
import tempfile
import time


_SYSTEMS = ("pendulum", "cycloid")
_DEFAULT_RANGE = {"pendulum": (1e-3, math.pi - 1e-3), "cycloid": (1e-3, math.pi)}
_SOLVERS = ("dopri8", "dopri5", "tsit5")
_BLOCK_CHUNKS = 4  # chunks per checkpoint/progress block


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, no usage dump, exit 2
        raise _UsageError(message)


def _parser():
    p = _Parser(
        prog="lagrax",
        description="Lagrangian mechanics by automatic differentiation.",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    s = sub.add_parser(
        "sweep",
        help="periods of many amplitudes against the exact ones",
        description=(
            "Period against amplitude for the simple pendulum (amplitude θ0 in rad, "
            "0 < θ0 < π) and Huygens' cycloidal pendulum (amplitude a = π − θ0 in "
            "rad, the rolling angle from the bottom, a = π is the cusp; integrated in "
            "u = sin(a/2)). g = r = R = 1, float64."
        ),
    )
    s.add_argument(
        "system",
        nargs="?",
        default="both",
        choices=(*_SYSTEMS, "both"),
        help="which system (default: both)",
    )
    s.add_argument("--count", type=int, default=2048, help="amplitudes per system")
    s.add_argument(
        "--min",
        type=float,
        default=None,
        dest="amin",
        help="smallest amplitude in rad (default 1e-3)",
    )
    s.add_argument(
        "--max",
        type=float,
        default=None,
        dest="amax",
        help="largest amplitude in rad (default π − 1e-3 pendulum, π cycloid)",
    )
    s.add_argument("--solver", default="dopri8", choices=_SOLVERS)
    s.add_argument("--rtol", type=float, default=1e-13)
    s.add_argument("--atol", type=float, default=1e-13)
    s.add_argument(
        "--method",
        default="quarter",
        choices=("quarter", "half", "full"),
        help="how much of each orbit to integrate (see lagrax.period; both systems "
        "are mirror-symmetric, so 'quarter' is exact and best conditioned near π)",
    )
    s.add_argument(
        "--chunk-size",
        type=int,
        default=128,
        help="lanes per compiled batch (default 128: on 2048 pendulum amplitudes, "
        "where step counts climb steeply towards π, 256 left only 83%% of the "
        "executed lane-steps useful, 128 gives 90%%)",
    )
    s.add_argument(
        "--out", default=None, help="write every amplitude to a .csv or .npz file"
    )
    s.add_argument("--plot", default=None, help="write a chart (.png, .pdf, .svg)")
    s.add_argument("--rows", type=int, default=7, help="table rows per system")
    s.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


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


def _validate(args):
    if args.command != "sweep":
        raise _UsageError("expected a command: `lagrax sweep [pendulum|cycloid|both]`")
    if args.count < 1:
        raise _UsageError(f"--count must be a positive integer; got {args.count}")
    if args.chunk_size < 1:
        raise _UsageError(f"--chunk-size must be positive; got {args.chunk_size}")
    if args.rows < 0:
        raise _UsageError(f"--rows must be >= 0; got {args.rows}")
    for name in ("rtol", "atol"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise _UsageError(f"--{name} must be a positive number; got {value}")
    systems = _SYSTEMS if args.system == "both" else (args.system,)
    ranges = {}
    for system in systems:
        lo = _DEFAULT_RANGE[system][0] if args.amin is None else args.amin
        hi = _DEFAULT_RANGE[system][1] if args.amax is None else args.amax
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi <= math.pi):
            raise _UsageError(
                f"amplitudes must satisfy 0 < --min <= --max <= π (rad); got "
                f"--min {lo} --max {hi} for the {system}"
            )
        ranges[system] = (lo, hi)
    if args.out is not None:
        _check_writable(args.out, "--out", (".csv", ".npz"))
    if args.plot is not None:
        _check_writable(args.plot, "--plot", (".png", ".pdf", ".svg"))
    return ranges


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


def _setup_jax():
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


@functools.cache
def _system(name):
    # Cached: the same Lagrangian object reuses the compiled sweep within a process.
    import jax.numpy as jnp

    from .systems import cycloid, pendulum

    if name == "pendulum":
        L = pendulum.lagrangian()
        return (
            L,
            lambda a: a,  # q0 = θ0
            lambda a: pendulum.pendulum_period(a),
            2 * math.pi,
        )
    L = cycloid.lagrangian_u()
    return (
        L,
        lambda a: jnp.sin(a / 2),  # u0 = cos(θ0/2) = sin(a/2)
        lambda a: cycloid.cycloid_period(a),
        4 * math.pi,
    )


def _sweep(system, lo, hi, args, checkpoint_dir, progress):
    import diffrax as dfx
    import jax
    import jax.numpy as jnp
    import numpy as np

    from ._period import sweep_periods

    solver = {"dopri8": dfx.Dopri8, "dopri5": dfx.Dopri5, "tsit5": dfx.Tsit5}[
        args.solver
    ]()
    L, to_q0, exact_fn, T0 = _system(system)
    amplitude = np.linspace(lo, hi, args.count)
    q0 = np.asarray(to_q0(jnp.asarray(amplitude)))
    block = args.chunk_size * len(jax.devices()) * _BLOCK_CHUNKS
    n_blocks = -(-args.count // block)
    parts = []
    useful = executed = 0
    start = time.perf_counter()
    for b in range(n_blocks):
        sl = slice(b * block, min((b + 1) * block, args.count))
        ckpt = (
            None
            if checkpoint_dir is None
            else os.path.join(checkpoint_dir, f"{system}-{b:05d}.npz")
        )
        if ckpt is not None and os.path.exists(ckpt):
            with np.load(ckpt) as f:
                part = {k: f[k] for k in f.files}
        else:
            res = sweep_periods(
                L,
                jnp.asarray(q0[sl]),
                solver=solver,
                rtol=args.rtol,
                atol=args.atol,
                method=args.method,
                chunk_size=args.chunk_size,
            )
            part = {
                "period": np.asarray(res.periods),
                "status": np.asarray(res.status),
                "steps": np.asarray(res.num_steps),
                "useful": np.asarray(res.lane_steps_useful),
                "executed": np.asarray(res.lane_steps_executed),
            }
            if ckpt is not None:
                _atomic_write(ckpt, lambda p, part=part: np.savez(p, **part))
        parts.append(part)
        useful += int(part["useful"])
        executed += int(part["executed"])
        progress(system, sl.stop, args.count)
    elapsed = time.perf_counter() - start
    period = np.concatenate([p["period"] for p in parts])
    exact = np.asarray(exact_fn(jnp.asarray(amplitude)))
    return {
        "system": system,
        "amplitude": amplitude,
        "q0": q0,
        "period": period,
        "T_over_T0": period / T0,
        "exact": exact,
        "rel_error": np.abs(period / exact - 1),
        "status": np.concatenate([p["status"] for p in parts]),
        "steps": np.concatenate([p["steps"] for p in parts]),
        "seconds": elapsed,
        "useful_fraction": useful / max(executed, 1),
    }


def _table(results, rows):
    import numpy as np

    from ._period import STATUS_CODES

    lines = [
        f"{'system':<9} {'amplitude':>10} {'period':>18} {'T/T0':>12} "
        f"{'exact':>18} {'rel. error':>10}  status"
    ]
    for r in results:
        n = len(r["amplitude"])
        picks = sorted(set(np.linspace(0, n - 1, min(rows, n)).round().astype(int)))
        for i in picks:
            code = int(r["status"][i])
            lines.append(
                f"{r['system']:<9} {r['amplitude'][i]:>10.6f} {r['period'][i]:>18.15f} "
                f"{r['T_over_T0'][i]:>12.9f} {r['exact'][i]:>18.15f} "
                f"{r['rel_error'][i]:>10.1e}  {STATUS_CODES[code]}"
            )
    lines.append("")
    for r in results:
        ok = r["status"] == 0
        worst = float(np.max(r["rel_error"][ok])) if ok.any() else float("nan")
        lines.append(
            f"{r['system']}: {len(ok)} amplitudes, {int((~ok).sum())} failed, max "
            f"relative error {worst:.1e}, {r['seconds']:.2f} s "
            f"(compile included), useful lane-steps {r['useful_fraction']:.0%}"
        )
    return "\n".join(lines)


def _write_out(path, results):
    import numpy as np

    from ._period import STATUS_CODES

    columns = ("amplitude", "q0", "period", "T_over_T0", "exact", "rel_error")
    if path.lower().endswith(".npz"):
        data = {
            "system": np.concatenate(
                [np.full(len(r["amplitude"]), r["system"]) for r in results]
            )
        }
        for c in (*columns, "status", "steps"):
            data[c] = np.concatenate([r[c] for r in results])
        _atomic_write(path, lambda p: np.savez(p, **data))
        return

    def write(p):
        with open(p, "w") as f:
            f.write("system," + ",".join(columns) + ",status,status_name,steps\n")
            for r in results:
                for i in range(len(r["amplitude"])):
                    values = ",".join(repr(float(r[c][i])) for c in columns)
                    code = int(r["status"][i])
                    f.write(
                        f"{r['system']},{values},{code},{STATUS_CODES[code]},"
                        f"{int(r['steps'][i])}\n"
                    )

    _atomic_write(path, write)


def _plot(path, results):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for r in results:
        ok = r["status"] == 0
        label = {
            "pendulum": "simple pendulum (amplitude θ₀)",
            "cycloid": "cycloidal pendulum (amplitude a = π − θ₀)",
        }[r["system"]]
        ax.plot(r["amplitude"][ok], r["T_over_T0"][ok], label=label)
    ax.set_xlabel("amplitude (rad)")
    ax.set_ylabel("T / T₀")
    ax.set_yscale("log")
    ax.set_title("Period against amplitude (lagrax sweep)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    ext = os.path.splitext(path)[1][1:]
    _atomic_write(path, lambda p: fig.savefig(p, format=ext, dpi=120))
    plt.close(fig)


def _run_sweep(args, ranges):
    import shutil

    _setup_jax()
    checkpoint_dir = None
    if args.out is not None:
        # Per-block checkpoints next to the output, keyed by everything that changes
        # the numbers: a rerun of the same command resumes; a different one restarts.
        checkpoint_dir = args.out + ".partial"
        manifest = {
            k: getattr(args, k)
            for k in ("count", "solver", "rtol", "atol", "method", "chunk_size")
        }
        manifest["ranges"] = {k: list(v) for k, v in ranges.items()}
        manifest_path = os.path.join(checkpoint_dir, "manifest.json")
        if os.path.isdir(checkpoint_dir):
            try:
                with open(manifest_path) as f:
                    same = json.load(f) == json.loads(json.dumps(manifest))
            except (OSError, ValueError):
                same = False
            if not same:
                shutil.rmtree(checkpoint_dir)
        if not os.path.isdir(checkpoint_dir):
            os.makedirs(checkpoint_dir)
            with open(manifest_path, "w") as f:
                json.dump(manifest, f)

    show = not args.quiet

    def progress(system, done, total):
        if show and total > args.chunk_size * _BLOCK_CHUNKS:
            end = "\n" if done == total else ""
            print(
                f"\r{system}: {done}/{total} amplitudes",
                end=end,
                file=sys.stderr,
                flush=True,
            )

    results = [
        _sweep(system, lo, hi, args, checkpoint_dir, progress)
        for system, (lo, hi) in ranges.items()
    ]
    print(_table(results, args.rows))
    if args.out is not None:
        _write_out(args.out, results)
        shutil.rmtree(checkpoint_dir, ignore_errors=True)
        print(f"wrote {args.out}")
    if args.plot is not None:
        _plot(args.plot, results)
        print(f"wrote {args.plot}")
    failed = sum(int((r["status"] != 0).sum()) for r in results)
    if failed:
        print(
            f"{failed} amplitudes failed: see the status column "
            "(lagrax.status_message(code) explains each code)",
            file=sys.stderr,
        )
        return 1
    return 0


def main(argv=None) -> int:
    """Entry point of the `lagrax` console script."""
    try:
        args = _parser().parse_args(argv)
        ranges = _validate(args)
    except _UsageError as e:
        print(f"lagrax: error: {e}", file=sys.stderr)
        return 2
    try:
        return _run_sweep(args, ranges)
    except KeyboardInterrupt:
        print(
            "\nlagrax: interrupted; rerun the same command to resume", file=sys.stderr
        )
        return 130
