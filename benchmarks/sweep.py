"""Periods per second over a pendulum amplitude sweep, against the exact period.

4096 amplitudes 0.01–3.1 rad (g = r = 1), float64, max relative error against the AGM
period. Side by side, in one invocation (each group in a fresh worker process, one
after the other):

- heyoka.py at its best on this machine: its scalar Taylor integrator with a terminal
  event on θ (direction negative, T = 4t, tol = eps) in a Python loop, pinned to one
  core; its batch mode at `recommended_simd_size()` (a non-terminal batch event whose
  callback records each lane's first crossing); and on the whole machine, 2 Python
  threads with one scalar or batch integrator each over half the amplitudes, and the
  batch mode in one process per core, each pinned, over its share (started together;
  all amplitudes over the slowest share's best time). All reported. "vs heyoka" is
  against heyoka.py's best on the same resources: one-core rows against its best
  one-core row, whole-machine rows against its best row of all.
- scipy `solve_ivp` DOP853 + terminal event, a Python loop (subsample, extrapolated);
- the naive diffrax baseline: hand-written `-sin θ`, Dopri8, `Event` with Newton root
  finding, one unsorted `jit(vmap(diffeqsolve))` batch;
- lagrax `sweep_periods`, methods "quarter", "half" and "matched" (the default), at
  rtol = atol = 1e-12 … 1e-14, with `Dopri8` and `lagrax.Taylor()` (order 20; the
  default solver `Taylor(fallback=Dopri8())` resolves to it for the pendulum), with
  the per-lane error estimate off (the kernel alone) and on (the default), and with
  every default (the "default" row), on one core (one JAX device, `taskset` to
  core 0) and on the whole machine (one JAX device per core).

For every lagrax row it prints periods/s, max relative error, steps per lane, the
useful fraction of lane-steps, ns per lane-step, and the ceiling: the time of the
vector field alone for the same number of stage evaluations (13 per Dopri8 step), so
that the loop's overhead can be read off. Compile time of each configuration is
measured on its own (first call, `jax.clear_caches()` before).

    python benchmarks/sweep.py [--quick]
    python benchmarks/sweep.py --gpu     # 1e4 … 1e6 lanes on the default JAX backend

`--gpu` also runs heyoka.py (one pinned core, and one process per core) on the same
machine's CPU where it is installed; where it is not (its wheel is ~100 MB), the GPU
rows are compared with heyoka.py's best rates in the committed `results/sweep.json`,
and the output says so.

Writes `benchmarks/results/sweep.json` and `sweep.png` (or `sweep_gpu.json`).
"""

import argparse
import functools
import json
import os
import platform
import subprocess
import sys
import time


# Cold compiles, as measured: the library's disk cache of executables off.
os.environ["LAGRAX_CACHE_DIR"] = ""


HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")
TOLS = (1e-12, 1e-13, 1e-14)


def _amplitudes(n):
    import numpy as np

    return np.linspace(0.01, 3.1, n)


def _exact(a):
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)  # the reference in float64, always

    from lagrax.systems import pendulum

    return np.asarray(pendulum.period(a))


def _best(fn, repeats, min_seconds=1.0):
    """The output and the shortest time of at least `repeats` calls, and of as many as
    fill `min_seconds`: a call of a few milliseconds varies from call to call (most
    with two JAX devices), so short calls are repeated for a second."""
    times, out = [], None
    start = time.perf_counter()
    while len(times) < repeats or time.perf_counter() - start < min_seconds:
        t = time.perf_counter()
        out = fn()
        try:
            import jax

            out = jax.block_until_ready(out)
        except Exception:
            pass
        times.append(time.perf_counter() - t)
    return out, min(times)


def _row(name, T, exact, seconds, **extra):
    import numpy as np

    T = np.asarray(T)
    ok = np.isfinite(T)
    err = float(np.max(np.abs(T[ok] / exact[: len(T)][ok] - 1))) if ok.any() else None
    return dict(
        name=name,
        periods_per_s=len(T) / seconds,
        seconds=seconds,
        max_rel_error=err,
        failed=int((~ok).sum()),
        n=len(T),
        **extra,
    )


# ------------------------------------------------------------------------ workers


def work_heyoka(args):
    import threading

    import heyoka as hy
    import numpy as np

    a = _amplitudes(args.n)
    exact = _exact(a)
    x, v = hy.make_vars("x", "v")
    system = hy.lagrangian(0.5 * v**2 + hy.cos(x), [x], [v])

    def scalar_integrator():
        ev = hy.t_event(x, direction=hy.event_direction.negative)
        return hy.taylor_adaptive(system, [1.0, 0.0], t_events=[ev])

    def scalar_loop(ta, amps):
        T = np.empty_like(amps)
        for i, a0 in enumerate(amps):
            ta.time = 0.0
            ta.state[:] = (a0, 0.0)
            ta.propagate_until(1e3)
            T[i] = 4 * ta.time
        return T

    B = hy.recommended_simd_size()

    def batch_integrator():
        """A batch integrator of B lanes and the loop that sweeps amplitudes with it
        (a non-terminal event records each lane's first crossing)."""
        first = np.full(B, np.nan)

        def record(ta, t, d_sgn, idx):
            if np.isnan(first[idx]):
                first[idx] = t

        ev = hy.nt_event_batch(x, record, direction=hy.event_direction.negative)
        tb = hy.taylor_adaptive_batch(
            system, np.array([[1.0] * B, [0.0] * B]), nt_events=[ev]
        )

        def batch(amps):
            T = np.full_like(amps, np.nan)
            for i in range(0, len(amps), B):
                k = min(B, len(amps) - i)
                tb.set_time(0.0)
                tb.state[0, :] = np.resize(amps[i : i + k], B)
                tb.state[1, :] = 0.0
                first[:] = np.nan
                t = 0.0
                while np.isnan(first).any():
                    t += 1.0
                    tb.propagate_until(t)
                T[i : i + k] = 4 * first[:k]
            return T

        return batch

    def two_threads(loops):
        halves = np.array_split(a, 2)

        def run():
            out = [None, None]

            def go(i):
                out[i] = loops[i](halves[i])

            ts = [threading.Thread(target=go, args=(i,)) for i in range(2)]
            for t in ts:
                t.start()
            for t in ts:
                t.join()
            return np.concatenate(out)

        run()
        return run

    rows = []
    if args.mode == "part":
        # One of `args.parts` processes, each pinned to its own core, sweeping its
        # share with the batch integrator from the same moment on (`--start-at`).
        batch = batch_integrator()
        share = np.array_split(a, args.parts)[args.part]
        truth = np.array_split(exact, args.parts)[args.part]
        batch(share[: 4 * B])
        time.sleep(max(0.0, args.start_at - time.time()))
        T, sec = _best(lambda: batch(share), args.repeats)
        err = float(np.max(np.abs(T / truth - 1)))
        failed = int((~np.isfinite(T)).sum())
        return [dict(seconds=sec, max_rel_error=err, n=len(share), failed=failed, B=B)]
    if args.mode == "scalar":
        ta = scalar_integrator()
        scalar_loop(ta, a[:64])
        T, sec = _best(lambda: scalar_loop(ta, a), args.repeats)
        rows.append(_row(f"heyoka.py {hy.__version__} scalar, 1 core", T, exact, sec))
        batch = batch_integrator()
        T, sec = _best(lambda: batch(a), args.repeats)
        rows.append(_row(f"heyoka.py batch (SIMD {B}), 1 core", T, exact, sec))
    else:
        scalars = [functools.partial(scalar_loop, scalar_integrator()) for _ in "ab"]
        T, sec = _best(two_threads(scalars), args.repeats)
        rows.append(_row("heyoka.py scalar, 2 threads", T, exact, sec))
        batches = [batch_integrator() for _ in "ab"]
        T, sec = _best(two_threads(batches), args.repeats)
        rows.append(_row(f"heyoka.py batch (SIMD {B}), 2 threads", T, exact, sec))
    return rows


def work_jax(args):
    import jax

    jax.config.update("jax_num_cpu_devices", args.devices)
    jax.config.update("jax_enable_x64", True)
    import diffrax as dfx
    import jax.numpy as jnp
    import numpy as np
    import optimistix as optx

    import lagrax
    from lagrax._eom.mechanics import _accelerations
    from lagrax._jaxpr.trig import vectorized_trig
    from lagrax.systems import pendulum

    a_np = _amplitudes(args.n)
    a = jnp.asarray(a_np)
    exact = _exact(a_np)
    L = pendulum.lagrangian()
    rows = []
    where = "1 core" if args.devices == 1 else f"{args.devices} devices"

    if args.devices == 1:
        from scipy.integrate import solve_ivp

        def f(t, y):
            return [y[1], -np.sin(y[0])]

        def turning(t, y):
            return y[1]

        turning.terminal, turning.direction = True, 1.0
        sub = a_np[:: 64 if not args.quick else 16]
        t0 = time.perf_counter()
        T = [
            2
            * solve_ivp(
                f, (0, 1e3), [x, 0.0], "DOP853", rtol=1e-13, atol=1e-13, events=turning
            ).t_events[0][0]
            for x in sub
        ]
        sec = (time.perf_counter() - t0) * len(a_np) / len(sub)
        err = float(np.max(np.abs(np.asarray(T) / _exact(sub) - 1)))
        rows.append(
            dict(
                name="scipy DOP853 loop, rtol 1e-13",
                periods_per_s=len(a_np) / sec,
                max_rel_error=err,
                failed=0,
                n=len(sub),
                note="subsample, extrapolated",
            )
        )

        event = dfx.Event(
            lambda t, y, args, **kw: -y[1],
            root_finder=optx.Newton(rtol=1e-12, atol=1e-12),
            direction=False,
        )

        @jax.jit
        @jax.vmap
        def naive(x):
            sol = dfx.diffeqsolve(
                dfx.ODETerm(lambda t, y, args: (y[1], -jnp.sin(y[0]))),
                dfx.Dopri8(),
                0.0,
                1e3,
                None,
                (x, 0.0 * x),
                stepsize_controller=dfx.PIDController(rtol=1e-13, atol=1e-13),
                event=event,
                max_steps=4096,
                throw=False,
            )
            return 2 * sol.ts[-1]

        naive(a)
        T, sec = _best(lambda: naive(a), args.repeats)
        rows.append(_row("naive diffrax vmap, rtol 1e-13", T, exact, sec))

        # The ceiling: the vector field alone, 13 evaluations per lane-step. Unfused
        # (`fuse=False`): alone in a loop the one-fusion form is the slower one; it
        # pays inside a step. With the sines the kernel's Runge-Kutta stages use
        # (`vectorized_trig`), so that the column compares like with like.
        def accel(x, v):
            z = jnp.zeros((), x.dtype)
            qddot, _ = _accelerations(L, x[None], v[None], z, fuse=False)
            return qddot[0]

        acc = jax.vmap(vectorized_trig(accel))
        evals = 13 * 26

        @jax.jit
        def field_only(x):
            def body(i, c):
                x, v = c
                return x + 1e-9 * acc(x, v), v

            return jax.lax.fori_loop(0, evals, body, (x, 0 * x))

        field_only(a)
        _, sec = _best(lambda: field_only(a), args.repeats)
        ceiling_ns = sec / (len(a_np) * evals / 13) * 1e9
    else:
        ceiling_ns = None

    dopri8, taylor = dfx.Dopri8(), lagrax.Taylor()
    configs = [
        ("quarter", 1e-12, False, dopri8),
        ("quarter", 1e-13, False, dopri8),
        ("half", 1e-13, False, dopri8),
        ("half", 1e-14, False, dopri8),
        ("matched", 1e-12, False, dopri8),
        ("matched", 1e-13, False, dopri8),
        ("matched", 1e-13, True, dopri8),
        ("quarter", 1e-13, False, taylor),
        ("quarter", 1e-14, False, taylor),
        ("half", 1e-14, False, taylor),
        ("matched", 1e-13, False, taylor),
        ("matched", 1e-14, False, taylor),
        ("matched", 1e-14, True, taylor),
        ("matched", 1e-13, True, None),  # every default: Taylor(fallback=Dopri8())
    ]
    if args.quick:
        configs = [c for c in configs if c[1] == 1e-13]
    for method, tol, estimate, solver in configs:
        run = lambda: lagrax.sweep_periods(
            L,
            a,
            method=method,
            rtol=tol,
            atol=tol,
            error_estimate=estimate,
            **({} if solver is None else {"solver": solver}),
        )
        jax.clear_caches()
        t0 = time.perf_counter()
        jax.block_until_ready(run())
        compile_s = time.perf_counter() - t0
        res, sec = _best(run, args.repeats)
        steps = float(np.mean(np.asarray(res.num_steps)))
        executed = float(res.lane_steps_executed)
        label = "" if estimate else ", no estimate"
        name = {id(taylor): "Taylor-20", id(dopri8): "Dopri8"}.get(
            id(solver), f"default ({type(res.solver).__name__})"
        )
        rows.append(
            _row(
                f"lagrax {name} {method} rtol {tol:g}{label}, {where}",
                res.periods,
                exact,
                sec,
                compile_s=compile_s,
                steps_per_lane=steps,
                useful_fraction=float(res.useful_fraction),
                ns_per_lane_step=sec / executed * 1e9 * args.devices,
                ceiling_ns_per_lane_step=ceiling_ns if solver is dopri8 else None,
                max_error_estimate=(
                    None
                    if res.error_estimate is None
                    else float(np.nanmax(np.asarray(res.error_estimate)))
                ),
            )
        )
    return rows


def work_gpu(args):
    """The defaults' sweep and two kernels alone on the default backend (a GPU), at
    `--gpu-sizes` amplitudes and `--gpu-lanes` lanes; each row printed as it is
    measured, and rows skipped once `--budget` seconds have passed."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import diffrax as dfx
    import jax.numpy as jnp

    import lagrax
    from lagrax.systems import pendulum

    L = pendulum.lagrangian()
    rows = []
    device = str(jax.devices()[0].device_kind)
    start = time.perf_counter()
    configs = (
        ("defaults", {}),  # the defaults' work: matched, Taylor, the estimate
        ("Taylor matched", dict(solver=lagrax.Taylor(), error_estimate=False)),
        ("Dopri8 quarter", dict(solver=dfx.Dopri8(), method="quarter")),
    )
    for n in args.gpu_sizes:
        a_np = _amplitudes(n)
        a = jnp.asarray(a_np)
        exact = _exact(a_np)
        for label, kw in configs:
            for lanes in args.gpu_lanes:
                if lanes > max(n, min(args.gpu_lanes)):
                    continue
                if time.perf_counter() - start > args.budget:
                    print(
                        f"budget spent: {label} n={n} lanes={lanes} skipped",
                        file=sys.stderr,
                        flush=True,
                    )
                    continue
                run = lambda: lagrax.sweep_periods(L, a, lanes=lanes, **kw)
                t0 = time.perf_counter()
                jax.block_until_ready(run())
                compile_s = time.perf_counter() - t0
                res, sec = _best(run, args.repeats)
                rows.append(
                    _row(
                        f"lagrax {label} n={n} lanes={lanes} on {device}",
                        res.periods,
                        exact,
                        sec,
                        compile_s=compile_s,
                        useful_fraction=float(res.useful_fraction),
                    )
                )
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    return rows


# --------------------------------------------------------------------------- main


def _heyoka_reference():
    """heyoka.py's best one-core and whole-machine rates from the committed CPU run
    (`results/sweep.json`), for a machine without heyoka.py (a GPU machine that
    cannot install it: its wheel is ~100 MB)."""
    path = os.path.join(RESULTS, "sweep.json")
    with open(path) as fh:
        meta = json.load(fh)["meta"]
    return dict(
        one_core=meta["best_heyoka_one_core_periods_per_s"],
        whole_machine=meta["best_heyoka_whole_machine_periods_per_s"],
        source=(
            "heyoka.py not installed here: its best rates from results/sweep.json, "
            f"measured on another machine ({meta['machine']})"
        ),
    )


def spawn(kind, n, repeats, quick, pin=None, **kw):
    cmd = [sys.executable, __file__, "--worker", kind, "--n", str(n)]
    cmd += ["--repeats", str(repeats)] + (["--quick"] if quick else [])
    for k, v in kw.items():
        cmd += [f"--{k}", str(v)]
    if pin is not None:
        cmd = ["taskset", "-c", str(pin)] + cmd
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        print(out.stderr[-3000:], file=sys.stderr)
        return []
    return json.loads(out.stdout.strip().splitlines()[-1])


def heyoka_processes(n, repeats, quick, parts):
    """heyoka.py's batch mode in `parts` processes at once, one per core, each over
    its share of the amplitudes: the rate is all amplitudes over the slowest share's
    best time (generous to it: the best times need not coincide)."""
    start = time.time() + 8.0  # after every process has built its integrator
    procs = []
    for i in range(parts):
        cmd = ["taskset", "-c", str(i), sys.executable, __file__, "--worker", "heyoka"]
        cmd += ["--mode", "part", "--part", str(i), "--parts", str(parts)]
        cmd += ["--start-at", str(start), "--n", str(n), "--repeats", str(repeats)]
        cmd += ["--quick"] if quick else []
        procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True))
    outs = [json.loads(p.communicate()[0].strip().splitlines()[-1])[0] for p in procs]
    if any(p.returncode for p in procs):
        return []
    sec = max(o["seconds"] for o in outs)
    return [
        dict(
            name=f"heyoka.py batch (SIMD {outs[0]['B']}), {parts} processes",
            periods_per_s=n / sec,
            seconds=sec,
            max_rel_error=max(o["max_rel_error"] for o in outs),
            failed=sum(o["failed"] for o in outs),
            n=n,
        )
    ]


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--quick", action="store_true")
    p.add_argument("--gpu", action="store_true")
    p.add_argument(
        "--gpu-sizes",
        type=int,
        nargs="+",
        default=[10_000, 100_000, 1_000_000],
        help="amplitudes per --gpu sweep (a small one checks the mode on a CPU)",
    )
    p.add_argument("--gpu-lanes", type=int, nargs="+", default=[65536, 262144])
    p.add_argument(
        "--budget", type=float, default=float("inf"), help="--gpu: seconds, then stop"
    )
    p.add_argument("--worker")
    p.add_argument("--mode", default="scalar")
    p.add_argument("--part", type=int, default=0)
    p.add_argument("--parts", type=int, default=1)
    p.add_argument("--start-at", type=float, default=0.0)
    p.add_argument("--devices", type=int, default=1)
    p.add_argument("--n", type=int, default=4096)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    if args.worker:
        fn = {"heyoka": work_heyoka, "jax": work_jax, "gpu": work_gpu}[args.worker]
        print(json.dumps(fn(args)))
        return
    reference = None
    if args.gpu:
        # heyoka.py on this machine's CPU, side by side, where it is installed; else
        # its best rates from the committed CPU run (another machine: said so).
        rows = []
        try:
            import heyoka  # noqa: F401
        except ImportError:
            reference = _heyoka_reference()
        else:
            cores = os.cpu_count()
            rows += spawn("heyoka", args.n, args.repeats, False, pin=0, mode="scalar")
            rows += heyoka_processes(args.n, args.repeats, False, cores)
        rows += work_gpu(args)
        name = "sweep_gpu.json"
    else:
        n = 1024 if args.quick else args.n
        r = 2 if args.quick else args.repeats
        cores = os.cpu_count()
        rows = []
        rows += spawn("heyoka", n, r, args.quick, pin=0, mode="scalar")
        rows += spawn("heyoka", n, r, args.quick, mode="threads")
        rows += heyoka_processes(n, r, args.quick, cores)
        rows += spawn("jax", n, r, args.quick, pin=0, devices=1)
        rows += spawn("jax", n, r, args.quick, devices=cores)
        name = "sweep_quick.json" if args.quick else "sweep.json"
    # Each row against heyoka.py's best on the same resources: one core, or the whole
    # machine (its threads and processes included, and its one-core rows: the best
    # use of the machine it has).
    whole = lambda name: any(w in name for w in ("devices", "threads", "processes"))
    heyoka = [x for x in rows if x["name"].startswith("heyoka")]
    best_one = max(
        (x["periods_per_s"] for x in heyoka if not whole(x["name"])), default=None
    )
    best_all = max((x["periods_per_s"] for x in heyoka), default=None)
    if reference is not None:
        best_one, best_all = reference["one_core"], reference["whole_machine"]
        print(f"vs heyoka: {reference['source']}")
    for x in rows:
        # (A GPU row against heyoka.py's best on one core, as the target is set.)
        best = best_all if whole(x["name"]) else best_one
        x["vs_heyoka"] = x["periods_per_s"] / best if best else None
        if args.gpu and best_all and not x["name"].startswith("heyoka"):
            x["vs_heyoka_whole_machine"] = x["periods_per_s"] / best_all
    print(
        f"{'':58s} {'periods/s':>10s} {'vs heyoka':>9s} {'max err':>8s} "
        f"{'steps':>6s} {'useful':>6s} {'ns/ls':>6s} {'ceil':>5s} {'compile':>7s}"
    )
    for x in rows:
        ratio = x["vs_heyoka"] if x["vs_heyoka"] is not None else float("nan")
        f = lambda k, fmt: (fmt % x[k]) if x.get(k) is not None else "-"
        print(
            f"{x['name']:58s} {x['periods_per_s']:10,.0f} {ratio:9.2f} "
            f"{f('max_rel_error', '%.1e'):>8s} {f('steps_per_lane', '%.1f'):>6s} "
            f"{f('useful_fraction', '%.3f'):>6s} {f('ns_per_lane_step', '%.0f'):>6s} "
            f"{f('ceiling_ns_per_lane_step', '%.0f'):>5s} {f('compile_s', '%.1f'):>7s}"
            + (f"  failed {x['failed']}" if x.get("failed") else "")
        )
    os.makedirs(RESULTS, exist_ok=True)
    import jax

    meta = dict(
        machine=f"{platform.machine()}, {os.cpu_count()} cores (shared)",
        processor=platform.processor(),
        jax=jax.__version__,
        best_heyoka_one_core_periods_per_s=best_one,
        best_heyoka_whole_machine_periods_per_s=best_all,
    )
    if reference is not None:
        meta["heyoka_reference"] = reference["source"]
    if args.gpu:
        meta["device"] = str(jax.devices()[0].device_kind)
        meta["date"] = time.strftime("%Y-%m-%d")
    with open(os.path.join(RESULTS, name), "w") as fh:
        json.dump(dict(meta=meta, results=rows), fh, indent=2)
    if args.gpu:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 0.32 * len(rows) + 1.2))
    names = [x["name"] for x in rows]
    speed = [x["periods_per_s"] for x in rows]
    colors = [
        "C1" if n.startswith("heyoka") else "C0" if "lagrax" in n else "C7"
        for n in names
    ]
    ax.barh(names, speed, color=colors)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel("periods per second (higher is better)")
    for i, x in enumerate(rows):
        if x.get("max_rel_error") is not None:
            ax.text(
                x["periods_per_s"],
                i,
                f" {x['max_rel_error']:.0e}",
                va="center",
                fontsize=7,
            )
    ax.set_title(
        f"Pendulum sweep, {rows[0]['n'] if rows else 0} amplitudes "
        "0.01–3.1 rad (label: max relative error)",
        fontsize=9,
    )
    ax.tick_params(axis="y", labelsize=7)
    fig.tight_layout()
    fig.savefig(
        os.path.join(RESULTS, "sweep.png" if not args.quick else "sweep_quick.png"),
        dpi=120,
    )
    print("wrote", os.path.join(RESULTS, name))


if __name__ == "__main__":
    main()
