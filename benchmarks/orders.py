r"""`simulate_batch`'s Taylor order against the tolerance and the system's size.

For each system, tier and order: the first call (trace + compile + one run; the
library's disk cache off) and, at each rtol = atol, the steady trajectories/s (the
best of interleaved rounds: every order and tolerance once per round, so that a
shared machine's load falls on all alike) and the largest absolute error of
$(q, \dot q)$ at $t = 10$ against heyoka.py in 80-bit long double at tol 1e-18 (the
reference of `trajectories.py`, cached in its `--cache`). Systems and releases are
`trajectories.py`'s (256 releases each; the double pendulum's are the first 256 of
its 1024). "heyoka" as an order is heyoka.py's rule, $K = \lceil -\ln(\text{tol})/2
+ 1\rceil$ (11, 13, 15, 16 at 1e-8, 1e-10, 1e-12, 1e-13), run as those orders.

Tiers: `LAGRAX_COMPACT=0` (the program specialized to the Lagrangian, its orders
unrolled) and `LAGRAX_COMPACT=2` (the compact program), each system and tier in a
fresh worker process under `taskset -c CORE`.

    python benchmarks/orders.py [--systems double_pendulum chain3 chain4]
        [--tiers 0 2] [--orders 12 14 16 20 24] [--tols 1e-8 1e-10 1e-12 1e-13]
        [--rounds 3]                       # results/orders.json
"""

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import trajectories as tr


HERE = os.path.dirname(os.path.abspath(__file__))
COUNT = 256


def heyoka_order(tol):
    return math.ceil(-math.log(tol) / 2 + 1)


def work(args):
    os.environ["LAGRAX_COMPACT"] = args.tier
    os.environ["LAGRAX_CACHE_DIR"] = ""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import lagrax

    q0, v0 = tr._initial(args.system, False)
    q0, v0 = q0[:COUNT], v0[:COUNT]
    with open(args.reference_file) as fh:
        ref = np.asarray(json.load(fh)["ys"])[:COUNT]
    L = tr._lagrax_lagrangian(args.system)
    q0j, v0j = jnp.asarray(q0), jnp.asarray(v0)

    def call(order, tol):
        sol = lagrax.simulate_batch(
            L, q0j, v0j, 0.0, tr.T1, solver=lagrax.Taylor(order=order),
            rtol=tol, atol=tol, max_steps=1 << 16, throw=False,
        )  # fmt: skip
        q1, w1 = (np.asarray(x[:, -1]) for x in sol.ys)
        return np.concatenate([q1, w1], axis=1), np.asarray(sol.stats["num_steps"])

    first = {}
    for k in args.orders:
        t, c = time.perf_counter(), time.process_time()
        call(k, args.tols[0])
        first[k] = (time.perf_counter() - t, time.process_time() - c)
        print(f"{args.system} tier {args.tier} order {k}: first call "
              f"{first[k][0]:.1f} s", file=sys.stderr, flush=True)  # fmt: skip
    best = {}
    for _ in range(args.rounds):
        for k in args.orders:
            for tol in args.tols:
                t, c = time.perf_counter(), time.process_time()
                ys, steps = call(k, tol)
                wall, cpu = time.perf_counter() - t, time.process_time() - c
                old = best.get((k, tol))
                if old is None or wall < old["wall_s"]:
                    ok = np.isfinite(ys).all()
                    err = float(np.max(np.abs(ys - ref))) if ok else None
                    best[(k, tol)] = dict(
                        wall_s=wall, cpu_s=cpu, max_error=err,
                        mean_steps=float(steps.mean()),
                    )  # fmt: skip
    rows = []
    for (k, tol), r in best.items():
        rows.append(dict(
            system=args.system, tier=args.tier, order=k, tol=tol,
            first_call_s=first[k][0], first_call_cpu_s=first[k][1],
            trajectories_per_s=COUNT / r["wall_s"],
            trajectories_per_cpu_s=COUNT / r["cpu_s"], **r,
        ))  # fmt: skip
    return rows


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--systems", nargs="+",
                   default=["double_pendulum", "chain3", "chain4"])  # fmt: skip
    p.add_argument("--tiers", nargs="+", default=["0", "2"], choices=["0", "2"])
    p.add_argument("--orders", nargs="+", default=["12", "14", "16", "20", "24"])
    p.add_argument("--tols", type=float, nargs="+",
                   default=[1e-8, 1e-10, 1e-12, 1e-13])  # fmt: skip
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--core", type=int, default=1)
    p.add_argument("--out", default=os.path.join(HERE, "results", "orders.json"))
    p.add_argument("--cache", default=os.path.join(
        tempfile.gettempdir(), "lagrax_trajectories_reference"))  # fmt: skip
    p.add_argument("--worker", action="store_true")
    p.add_argument("--system")
    p.add_argument("--tier")
    p.add_argument("--reference-file")
    args = p.parse_args()
    orders = []
    for o in args.orders:  # "heyoka": heyoka.py's rule at each tolerance
        ks = [heyoka_order(t) for t in args.tols] if o == "heyoka" else [int(o)]
        orders += [k for k in ks if k not in orders]
    args.orders = orders
    if args.worker:
        print(json.dumps(work(args)))
        return
    rows = []
    if os.path.exists(args.out):
        with open(args.out) as fh:
            rows = json.load(fh)["rows"]
    for system in args.systems:
        ref_args = argparse.Namespace(cache=args.cache, quick=False, repeats=1)
        ref = tr.reference(ref_args, system)
        path = os.path.join(tempfile.mkdtemp(), "ref.json")
        with open(path, "w") as fh:
            json.dump(ref, fh)
        for tier in args.tiers:
            cmd = ["taskset", "-c", str(args.core), sys.executable, __file__,
                   "--worker", "--system", system, "--tier", tier,
                   "--reference-file", path, "--rounds", str(args.rounds),
                   "--orders", *map(str, orders),
                   "--tols", *map(str, args.tols)]  # fmt: skip
            out = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
            if out.returncode:
                print(f"  ({system} tier {tier} failed)", file=sys.stderr)
                continue
            new = json.loads(out.stdout.strip().splitlines()[-1])
            done = {(r["system"], r["tier"], r["order"], r["tol"]) for r in new}
            rows = [
                r
                for r in rows
                if (r["system"], r["tier"], r["order"], r["tol"]) not in done
            ]
            rows += new  # fmt: skip
            with open(args.out, "w") as fh:
                json.dump(dict(rows=rows, date=time.strftime("%Y-%m-%d")), fh,
                          indent=1)  # fmt: skip
            _print(new)


def _print(rows):
    print("system tier order tol | first s | traj/s (cpu) | steps | max err")
    for r in sorted(rows, key=lambda r: (r["tol"], r["order"])):
        err = r["max_error"]
        print(f"{r['system']} {r['tier']} {r['order']:2d} {r['tol']:.0e} | "
              f"{r['first_call_s']:6.1f} | {r['trajectories_per_s']:8.0f} "
              f"({r['trajectories_per_cpu_s']:8.0f}) | {r['mean_steps']:7.1f} | "
              f"{'fail' if err is None else f'{err:.1e}'}", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
