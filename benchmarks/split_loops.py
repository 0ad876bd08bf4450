"""XLA's split loops: `simulate_batch`'s compact program compiled in the process
against compiled apart, in a process that may use every core.

XLA's CPU client splits each large loop of a program into parts run in parallel on
its thread pool, sized from the cores the process may use when JAX starts. The
library compiles `simulate_batch`'s compact programs (kept once per machine,
`executables.program`) in a process of its own with a pool of one thread
(`lagrax._cache.apart`) where a program compiled in the process would be split.
Here, in one fresh unpinned process per system (`LAGRAX_COMPACT=2`, an empty disk
cache of its own), the library's first call compiles the compact program apart;
then the same program is compiled in the process (split), and the two executables
run alternately on the same arguments (`--repeats` rounds; min and median of the
wall and CPU seconds), their outputs compared bit for bit; the compile times of
both, the program already traced (apart: its export, the worker's start, its
compile). The split loops are
counted in each executable's optimized HLO (`outer_dimension_partitions`).

- `double_pendulum`: `simulate_batch` of 1024 releases from rest, θ1, θ2 in [-1, 1],
  t = 10, rtol = atol = 1e-10;
- `chain4` (`chainN`): N unit pendulums, 256 releases in ±0.5 rad, t = 10, `Taylor()`,
  rtol = atol = 3e-12.

    python benchmarks/split_loops.py [--systems double_pendulum chain4 chain6]
        [--repeats 5]

Results: `results/split_loops.json`.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time


HERE = os.path.dirname(os.path.abspath(__file__))


def _call(name):
    """The library call that runs the compact program of system `name`."""
    import numpy as np

    import lagrax

    sys.path.insert(0, HERE)
    import taylor_coefficients as tc

    L, n = tc.lagrangian(name)
    rng = np.random.default_rng(0)
    if name == "double_pendulum":
        q0 = rng.uniform(-1.0, 1.0, (1024, n))
        kw = dict(rtol=1e-10, atol=1e-10)
    else:
        q0 = rng.uniform(-0.5, 0.5, (256, n))
        kw = dict(solver=lagrax.Taylor(), rtol=3e-12, atol=3e-12)
    return lambda: lagrax.simulate_batch(L, q0, np.zeros_like(q0), 0.0, 10.0, **kw).ys


def worker(name, repeats):
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    from lagrax import _compat
    from lagrax._cache import apart as _apart, executables

    captured = []
    call = executables.call

    def spy(jitted, static, out_tree, *args):
        captured.append((jitted, args))
        return call(jitted, static, out_tree, *args)

    executables.call = spy
    run = _call(name)
    t = time.perf_counter()
    jax.block_until_ready(run())
    first = time.perf_counter() - t
    stats = dict(executables.STATS)
    (jitted, args), *_ = captured
    apart = next(iter(executables._LOADED.values()))[0]  # (the first program's)
    t = time.perf_counter()
    here = jitted.lower(*args).compile()
    compile_here = time.perf_counter() - t
    t = time.perf_counter()
    again = _apart.compile_apart(*executables._PLAIN[jitted], args)
    compile_apart = time.perf_counter() - t if again is not None else None
    count = lambda c: c.as_text().count('outer_dimension_partitions":["')
    outs = {}
    wall = {"apart": [], "here": []}
    cpu = {"apart": [], "here": []}
    for _ in range(repeats):
        for side, exe in (("apart", apart), ("here", here)):
            t, p = time.perf_counter(), time.process_time()
            outs[side] = jax.block_until_ready(exe(*args))
            wall[side].append(time.perf_counter() - t)
            cpu[side].append(time.process_time() - p)
    same = all(
        np.array_equal(a, b, equal_nan=True)
        for a, b in zip(jax.tree.leaves(outs["apart"]), jax.tree.leaves(outs["here"]))
    )
    return dict(
        system=name,
        cores=len(os.sched_getaffinity(0)),
        splits_here=_compat.splits_loops(),
        stats=stats,
        first_call_s=first,
        compile_here_s=compile_here,
        compile_apart_s=compile_apart,
        split_loops={"apart": count(apart), "here": count(here)},
        wall_s={k: [min(v), statistics.median(v)] for k, v in wall.items()},
        cpu_s={k: [min(v), statistics.median(v)] for k, v in cpu.items()},
        identical=same,
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--systems", nargs="+", default=["double_pendulum", "chain4"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.repeats)))
        return
    rows = []
    for name in args.systems:
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, LAGRAX_CACHE_DIR=cache, LAGRAX_COMPACT="2")
            for var in ("PJRT_NPROC", "NPROC", "JAX_COMPILATION_CACHE_DIR"):
                env.pop(var, None)
            cmd = [
                sys.executable,
                __file__,
                "--worker",
                name,
                "--repeats",
                str(args.repeats),
            ]
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            print(proc.stderr[-3000:], file=sys.stderr)
            raise SystemExit(f"{name}: the worker failed")
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(row)
        w, c = row["wall_s"], row["cpu_s"]
        print(
            f"{name}: {row['cores']} cores, split loops here/apart "
            f"{row['split_loops']['here']}/{row['split_loops']['apart']}; first call "
            f"{row['first_call_s']:.2f} s; compile here / apart (traced) "
            f"{row['compile_here_s']:.2f} / {row['compile_apart_s'] or 0:.2f} s; "
            f"steady wall apart {w['apart'][0]:.3f}-"
            f"{w['apart'][1]:.3f} s, here {w['here'][0]:.3f}-{w['here'][1]:.3f} s "
            f"(here/apart {w['here'][0] / w['apart'][0]:.2f}); CPU apart "
            f"{c['apart'][0]:.3f}, here {c['here'][0]:.3f} s; identical "
            f"{row['identical']}; {row['stats']}",
            flush=True,
        )
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    with open(os.path.join(HERE, "results", "split_loops.json"), "w") as fh:
        json.dump(dict(date=time.strftime("%Y-%m-%d"), rows=rows), fh, indent=1)


if __name__ == "__main__":
    main()
