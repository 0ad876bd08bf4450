"""Where a compact trajectory's time goes: `simulate_batch` on its compact tier against
heyoka.py's compact (and default) mode, at equal error.

For each system (the releases, reference and error of `trajectories.py`: the largest
absolute error of $(q, \\dot q)$ at $t = 10$ against heyoka.py in 80-bit long double),
each side runs at the loosest tolerance of a half-decade grid whose error stays under
`--bound`, and the time of a batch is cut into

- steps: per release (mean) and lane-iterations (`simulate_batch`: its lanes refill
  from a queue, so the loop's iterations are a greedy schedule of the releases' step
  counts onto `--width` lanes; heyoka.py: batches of its SIMD width, each as long as
  its slowest lane); utilization = steps / lane-iterations;
- per lane-iteration: the whole step (the batch's time less the fixed overhead, over
  the lane-iterations); for lagrax also the Taylor coefficients alone (the compact
  program in a loop of coefficient computations over `--width` lanes) and the rest of
  the step (step length, polynomials, saving, refill: the difference);
- fixed overhead: lagrax's call that ends after one step (`t1` = 1e-9), the first call
  in a process whose disk cache holds the executable (load, tape, run); heyoka.py's
  build;
- side by side: heyoka.py's compact mode and lagrax's compact tier, each at its
  tolerance, timed alternately in one process (`--repeats` rounds; min, median,
  max), the headline ratio on a shared machine.

Every group runs in a fresh process pinned to `--core`; lagrax on
`LAGRAX_COMPACT=2` (its compact tier) with a disk cache of its own, filled by the
first process. Results: `results/compact_steps.json`.

    python benchmarks/compact_steps.py [--systems chain4 ...] [--bound 1e-9]
        [--width 64] [--order 16] [--core 1] [--heyoka-default-max 6]
"""

import argparse
import heapq
import json
import os
import subprocess
import sys
import tempfile
import time


HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

# (`trajectories` turns the library's disk cache off for its own cold timings; the
# executable on disk is part of what is measured here.)
_CACHE = os.environ.get("LAGRAX_CACHE_DIR")
import trajectories as tr  # noqa: E402


if _CACHE is None:
    os.environ.pop("LAGRAX_CACHE_DIR", None)
else:
    os.environ["LAGRAX_CACHE_DIR"] = _CACHE


def _error(ys, ref):
    import numpy as np

    return float(np.max(np.abs(np.asarray(ys) - np.asarray(ref))))


def lane_iterations(steps, width):
    """Iterations of a loop of `width` lanes that refill in order from the queue of
    releases with these step counts (lanes finishing together refill in lane order)."""
    free = [(0, lane) for lane in range(min(width, len(steps)))]
    heapq.heapify(free)
    end = 0
    for n in steps:
        t, lane = heapq.heappop(free)
        end = max(end, t + int(n))
        heapq.heappush(free, (t + int(n), lane))
    return end


# ----------------------------------------------------------------------- heyoka.py


def work_heyoka(args):
    import heyoka as hy
    import numpy as np

    hy.llvm_state.set_diskcache_enabled(False)
    q0, v0 = tr._initial(args.system, False)
    y0 = np.concatenate([q0, v0], 1)
    ref = np.asarray(json.load(open(args.reference))["ys"])
    n = q0.shape[1]
    B = hy.recommended_simd_size()

    def run(tb):
        out, steps, lane_its = np.empty_like(y0), [], 0
        for i in range(0, len(y0), B):
            idx = np.resize(np.arange(i, min(i + B, len(y0))), B)
            tb.set_time(0.0)
            tb.state[:] = y0[idx].T
            tb.propagate_until(tr.T1)
            res = tb.propagate_res
            steps += [r[3] for r in res[: min(B, len(y0) - i)]]
            lane_its += B * max(r[3] for r in res)
            out[i : i + B] = tb.state.T[: min(B, len(y0) - i)]
        return out, np.asarray(steps), lane_its

    rows = []
    for compact in (True, False) if n <= args.heyoka_default_max else (True,):
        for tol in tr._tolerances(args.bound):
            hy.llvm_state.clear_memcache()
            t = time.perf_counter()
            tb = hy.taylor_adaptive_batch(
                tr._heyoka_system(args.system), np.zeros((2 * n, B)), tol=tol,
                compact_mode=compact,
            )  # fmt: skip
            build = time.perf_counter() - t
            ys, steps, lane_its = run(tb)
            if _error(ys, ref) <= args.bound:
                break
        best = float("inf")
        for _ in range(args.repeats):
            t = time.perf_counter()
            ys, steps, lane_its = run(tb)
            best = min(best, time.perf_counter() - t)
        rows.append(dict(
            side="heyoka.py " + ("compact" if compact else "default"), tol=tol,
            order=tb.order, error=_error(ys, ref), build_s=build, run_s=best,
            steps=float(steps.mean()), lane_iterations=int(lane_its),
            utilization=float(steps.sum() / lane_its), width=B,
            lane_iteration_us=best / lane_its * 1e6,
        ))  # fmt: skip
    return rows


# -------------------------------------------------------------------------- lagrax


def _lagrax(args):
    import jax

    jax.config.update("jax_enable_x64", True)
    import lagrax

    L = tr._lagrax_lagrangian(args.system)
    q0, v0 = tr._initial(args.system, False)

    def call(tol, t1=tr.T1):
        sol = lagrax.simulate_batch(
            L, q0, v0, 0.0, t1, solver=lagrax.Taylor(order=args.order), rtol=tol,
            atol=tol, max_steps=1 << 16, throw=False, lanes=args.width,
        )  # fmt: skip
        return jax.block_until_ready(sol)

    return jax, call


def _best(fn, repeats):
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def work_lagrax(args):
    import numpy as np

    t = time.perf_counter()
    jax, call = _lagrax(args)
    import_s = time.perf_counter() - t
    ref = np.asarray(json.load(open(args.reference))["ys"])

    def ys_of(sol):
        return np.concatenate(
            [np.asarray(sol.ys[0][:, -1]), np.asarray(sol.ys[1][:, -1])], 1
        )

    t = time.perf_counter()
    call(args.bound)
    first = time.perf_counter() - t
    for tol in tr._tolerances(args.bound):
        sol = call(tol)
        if _error(ys_of(sol), ref) <= args.bound:
            break
    run = _best(lambda: call(tol), args.repeats)
    fixed = _best(lambda: call(tol, 1e-9), args.repeats)
    steps = np.asarray(sol.stats["num_steps"])
    its = lane_iterations(steps, args.width)
    lane_its = its * min(args.width, len(steps))
    coef_us = _coefficient_cost(jax, args)
    whole_us = (run - fixed) / lane_its * 1e6
    return [dict(
        side="lagrax compact", tol=tol, order=args.order, error=_error(ys_of(sol), ref),
        import_s=import_s, first_call_s=first, run_s=run, fixed_s=fixed,
        steps=float(steps.mean()), lane_iterations=int(lane_its),
        utilization=float(steps.sum() / lane_its), width=args.width,
        lane_iteration_us=whole_us, coefficients_us=coef_us,
        rest_us=whole_us - coef_us,
    )]  # fmt: skip


def _coefficient_cost(jax, args, steps=10, repeats=7):
    """Microseconds per lane-step of the compact coefficients alone (the tape
    `simulate_batch` builds, `--width` lanes, the loop's compile options)."""
    import jax.numpy as jnp
    import numpy as np

    from lagrax._jaxpr.canonical import canonical_lagrangian
    from lagrax._jaxpr.fusion import elemental_options
    from lagrax._taylor import compact
    from lagrax._trajectory import batch

    n = tr.SYSTEMS[args.system]["n"]
    L_c, consts = canonical_lagrangian(
        tr._lagrax_lagrangian(args.system), jnp.float64, n
    )
    tape, _ = batch._tape(L_c, tuple(consts), None, n, jnp.float64)
    W, K = args.width, args.order
    rng = np.random.default_rng(0)
    t = jnp.asarray(rng.uniform(0, 1, W))
    ys = jnp.asarray(rng.uniform(-0.5, 0.5, (2 * n, W)))
    sigma = jnp.ones(W)

    def run(t, ys, sigma, tape):
        def body(i, ys):
            cs = compact.compact_coefficients(tape, K, t, list(ys), [sigma], trig=True)
            return ys + 1e-6 * jnp.stack([c[-1] for c in cs])

        return jax.lax.fori_loop(0, steps, body, ys)

    fn = jax.jit(run, compiler_options=elemental_options()).lower(t, ys, sigma, tape)
    fn = fn.compile()
    jax.block_until_ready(fn(t, ys, sigma, tape))
    best = _best(lambda: jax.block_until_ready(fn(t, ys, sigma, tape)), repeats)
    return best / steps / W * 1e6


def work_lagrax_first(args):
    """The first call in a process whose disk cache holds the executable: import,
    first call."""
    t = time.perf_counter()
    jax, call = _lagrax(args)
    import_s = time.perf_counter() - t
    t = time.perf_counter()
    call(args.tol)
    first = time.perf_counter() - t
    return [dict(side="lagrax compact, executable on disk", tol=args.tol,
                 import_s=import_s, first_call_s=first)]  # fmt: skip


def work_pair(args):
    """heyoka.py's compact mode and lagrax's compact tier at their tolerances,
    timed alternately in one process (`--repeats` rounds): a shared machine's load
    then weighs on both alike."""
    import heyoka as hy
    import numpy as np

    jax, call = _lagrax(args)
    call(args.tol)
    q0, v0 = tr._initial(args.system, False)
    y0 = np.concatenate([q0, v0], 1)
    n = q0.shape[1]
    B = hy.recommended_simd_size()
    tb = hy.taylor_adaptive_batch(
        tr._heyoka_system(args.system), np.zeros((2 * n, B)), tol=args.heyoka_tol,
        compact_mode=True,
    )  # fmt: skip

    def heyoka_run():
        for i in range(0, len(y0), B):
            idx = np.resize(np.arange(i, min(i + B, len(y0))), B)
            tb.set_time(0.0)
            tb.state[:] = y0[idx].T
            tb.propagate_until(tr.T1)

    # Wall and CPU seconds: on a shared core the CPU seconds are the steadier.
    times = {"heyoka.py compact": [], "lagrax compact": []}
    cpu = {"heyoka.py compact": [], "lagrax compact": []}
    for _ in range(args.repeats):
        for side, fn in (("heyoka.py compact", heyoka_run),
                         ("lagrax compact", lambda: call(args.tol))):  # fmt: skip
            t, c = time.perf_counter(), time.process_time()
            fn()
            times[side].append(time.perf_counter() - t)
            cpu[side].append(time.process_time() - c)
    rows = [
        dict(
            side=f"{side}, alternated",
            run_s=min(ts),
            run_median_s=float(np.median(ts)),
            run_max_s=max(ts),
            run_cpu_s=min(cpu[side]),
            run_cpu_median_s=float(np.median(cpu[side])),
        )
        for side, ts in times.items()
    ]
    ratio = lambda d, f: float(f(d["lagrax compact"]) / f(d["heyoka.py compact"]))
    rows.append(
        dict(
            side="lagrax / heyoka.py compact, alternated",
            ratio_min=ratio(times, min),
            ratio_median=ratio(times, np.median),
            ratio_cpu_min=ratio(cpu, min),
            ratio_cpu_median=ratio(cpu, np.median),
        )
    )
    return rows


WORKERS = dict(
    heyoka=work_heyoka,
    lagrax=work_lagrax,
    lagrax_first=work_lagrax_first,
    pair=work_pair,
)


def spawn(args, kind, system, env=None, **extra):
    cmd = ["taskset", "-c", str(args.core), sys.executable, __file__, "--worker", kind]
    cmd += ["--system", system, "--reference", reference(system)]
    for key in ("bound", "width", "order", "repeats", "heyoka_default_max"):
        cmd += [f"--{key.replace('_', '-')}", str(getattr(args, key))]
    for key, value in extra.items():
        cmd += [f"--{key.replace('_', '-')}", str(value)]
    out = subprocess.run(
        cmd, stdout=subprocess.PIPE, text=True, env={**os.environ, **(env or {})}
    )
    if out.returncode:
        print(f"  ({kind} {system} failed)", file=sys.stderr)
        return []
    return json.loads(out.stdout.strip().splitlines()[-1])


def reference(system):
    """The long-double reference of `trajectories.py` (computed once, cached)."""
    path = os.path.join(tempfile.gettempdir(), "lagrax_trajectories_reference",
                        f"{system}_tol{tr.REFERENCE_TOL:g}.json")  # fmt: skip
    if not os.path.exists(path):
        os.makedirs(os.path.dirname(path), exist_ok=True)
        out = subprocess.run(
            [sys.executable, os.path.join(HERE, "trajectories.py"), "--worker",
             "reference", "--system", system, "--where", "machine"],
            stdout=subprocess.PIPE, text=True, check=True,
        )  # fmt: skip
        with open(path, "w") as fh:
            fh.write(out.stdout.strip().splitlines()[-1])
    return path


def main():
    p = argparse.ArgumentParser()
    p.add_argument(
        "--systems",
        nargs="+",
        default=["double_pendulum", "chain2", "chain4", "chain6", "chain8"],
    )
    p.add_argument("--bound", type=float, default=1e-9)
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--order", type=int, default=16)
    p.add_argument("--core", type=int, default=1)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument(
        "--heyoka-default-max",
        type=int,
        default=6,
        help="the largest n whose heyoka.py default mode is built",
    )
    p.add_argument("--worker")
    p.add_argument("--system")
    p.add_argument("--reference")
    p.add_argument("--tol", type=float)
    p.add_argument("--heyoka-tol", type=float)
    args = p.parse_args()
    if args.worker:
        print(json.dumps(WORKERS[args.worker](args)))
        return
    rows = []
    for system in args.systems:
        with tempfile.TemporaryDirectory() as cache:
            env = dict(LAGRAX_COMPACT="2", LAGRAX_CACHE_DIR=cache)
            out = spawn(args, "heyoka", system) + spawn(args, "lagrax", system, env)
            lx = [r for r in out if r["side"] == "lagrax compact"]
            hy = [r for r in out if r["side"] == "heyoka.py compact"]
            if lx:
                out += spawn(args, "lagrax_first", system, env, tol=lx[0]["tol"])
            if lx and hy:
                out += spawn(args, "pair", system, env, tol=lx[0]["tol"],
                             heyoka_tol=hy[0]["tol"])  # fmt: skip
        for r in out:
            r["system"] = system
            print(json.dumps(r), flush=True)
        rows += out
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE,
                            capture_output=True, text=True).stdout.strip()  # fmt: skip
    report = dict(date=time.strftime("%Y-%m-%d"), commit=commit, argv=sys.argv[1:],
                  rows=rows)  # fmt: skip
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    with open(os.path.join(HERE, "results", "compact_steps.json"), "w") as fh:
        json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main()
