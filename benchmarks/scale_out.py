"""Scaling out: periods/s of one sweep on 1 process × 1 device, 1 process × 2 devices
and 2 processes × 1 device (jax.distributed, gloo collectives on 127.0.0.1).

The same sweep every time: pendulum amplitudes 0.01–3.1 rad, `method="quarter"`,
Dopri8, rtol = atol = 1e-13, the same lanes per device; every configuration is
checked against the exact AGM period and against the one-device periods (bit for bit
where the lanes are the same). Each configuration runs in fresh processes, one after
the other, in one invocation of this script: compare the ratios within a run.

    python benchmarks/scale_out.py                  # 16384 amplitudes
    python benchmarks/scale_out.py --count 4096 --rounds 1

Writes `benchmarks/results/scale_out.json`. Timing: one warm-up call (compilation,
reported on its own), then the best and median of `--repeats` calls, each between two
barriers across processes (`multihost_utils.sync_global_devices`), timed on process 0;
`--rounds` runs every configuration again in turn and keeps each one's best round.
"""

import argparse
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import time


# Cold compiles, as measured: the library's disk cache of executables off.
os.environ["LAGRAX_CACHE_DIR"] = ""


HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
CONFIGS = ((1, 1), (1, 2), (2, 1))  # (processes, devices per process)


def worker(args):
    import jax

    jax.config.update("jax_num_cpu_devices", args.devices)
    jax.config.update("jax_enable_x64", True)
    if args.processes > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(
            coordinator_address=f"127.0.0.1:{args.port}",
            num_processes=args.processes,
            process_id=args.process_id,
            initialization_timeout=120,
            heartbeat_timeout_seconds=60,
        )
    import jax.numpy as jnp
    import numpy as np
    from jax.experimental import multihost_utils

    import lagrax
    from lagrax.systems import pendulum

    L = pendulum.lagrangian()
    q0 = jnp.linspace(0.01, 3.1, args.count)

    def sweep():
        multihost_utils.sync_global_devices("before")
        t = time.perf_counter()
        res = lagrax.sweep_periods(
            L, q0, method="quarter", lanes=args.lanes, rtol=1e-13, atol=1e-13
        )
        jax.block_until_ready(res)
        multihost_utils.sync_global_devices("after")
        return time.perf_counter() - t, res

    compile_s, res = sweep()
    times = [sweep()[0] for _ in range(args.repeats)]
    periods = np.asarray(res.periods)
    exact = np.asarray(pendulum.period(np.asarray(q0)))
    if jax.process_index() == 0:
        np.save(args.periods, periods)
        print(
            "RESULT "
            + json.dumps(
                {
                    "processes": args.processes,
                    "devices_per_process": args.devices,
                    "devices": len(jax.devices()),
                    "first_call_s": compile_s,
                    "best_s": min(times),
                    "median_s": statistics.median(times),
                    "periods_per_s": args.count / min(times),
                    "failed": int(np.sum(np.asarray(res.status) != 0)),
                    "max_rel_error": float(np.nanmax(np.abs(periods / exact - 1))),
                    "useful_fraction": float(res.useful_fraction),
                }
            ),
            flush=True,
        )


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def machine():
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    import jax

    return {
        "cpu": model,
        "cores_available": len(os.sched_getaffinity(0)),
        "gpu": "none",
        "python": platform.python_version(),
        "jax": jax.__version__,
        "note": "shared 2-core x86-64 CPU (other jobs may run beside this one)",
    }


def run_config(processes, devices, args, tmp):
    port = free_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    periods = os.path.join(tmp, f"periods-{processes}x{devices}.npy")
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                __file__,
                "--worker",
                "--processes",
                str(processes),
                "--devices",
                str(devices),
                "--process-id",
                str(i),
                "--port",
                str(port),
                "--count",
                str(args.count),
                "--lanes",
                str(args.lanes),
                "--repeats",
                str(args.repeats),
                "--periods",
                periods,
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(processes)
    ]
    outs = [p.communicate(timeout=1800) for p in procs]
    for p, (out, err) in zip(procs, outs):
        if p.returncode != 0:
            raise SystemExit(f"{processes}x{devices} failed:\n{err[-3000:]}")
    line = next(x for x in outs[0][0].splitlines() if x.startswith("RESULT "))
    result = json.loads(line[len("RESULT ") :])
    return result, periods


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--count", type=int, default=16384)
    p.add_argument("--lanes", type=int, default=128)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--out", default=os.path.join(HERE, "results", "scale_out.json"))
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--processes", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--devices", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--process-id", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--periods", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        return worker(args)

    import tempfile

    import numpy as np

    best = {}
    with tempfile.TemporaryDirectory() as tmp:
        periods = {}
        # Rounds alternate the configurations, so that a burst of load from other jobs
        # on a shared machine does not fall on one of them only; each keeps its best.
        for k in range(args.rounds):
            for processes, devices in CONFIGS:
                result, path = run_config(processes, devices, args, tmp)
                periods[(processes, devices)] = np.load(path)
                result["rounds"] = [result["periods_per_s"]]
                key = (processes, devices)
                if key in best:
                    result["rounds"] = best[key]["rounds"] + result["rounds"]
                if key not in best or result["periods_per_s"] > max(
                    best[key]["rounds"]
                ):
                    best[key] = result
                else:
                    best[key]["rounds"] = result["rounds"]
                print(
                    f"round {k + 1}: {processes} process(es) × {devices} device(s): "
                    f"{result['periods_per_s']:,.0f} periods/s",
                    flush=True,
                )
        rows = [best[c] for c in CONFIGS]
        base = rows[0]["periods_per_s"]
        for row in rows:
            row["speedup"] = row["periods_per_s"] / base
            row["efficiency"] = row["speedup"] / row["devices"]
        same = np.array_equal(periods[(1, 2)], periods[(2, 1)], equal_nan=True)
        vs_one = float(np.nanmax(np.abs(periods[(2, 1)] / periods[(1, 1)] - 1)))
    report = {
        "what": (
            f"{args.count} pendulum amplitudes 0.01-3.1 rad, sweep_periods "
            f"method='quarter', Dopri8, rtol=atol=1e-13, lanes={args.lanes} "
            "per device; best of repeats, best of rounds"
        ),
        "command": "python benchmarks/scale_out.py "
        + " ".join(a for a in sys.argv[1:]),
        "machine": machine(),
        "rows": rows,
        "two_processes_equal_one_process_two_devices_bitwise": bool(same),
        "max_rel_diff_two_processes_vs_one_device": vs_one,
    }
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=2)
    print()
    print(f"{'configuration':<28} {'periods/s':>10} {'speed-up':>9} {'efficiency':>10}")
    for row in rows:
        name = f"{row['processes']} proc × {row['devices_per_process']} device"
        print(
            f"{name:<28} {row['periods_per_s']:>10,.0f} {row['speedup']:>9.2f} "
            f"{row['efficiency']:>10.0%}"
        )
    print(f"2 procs × 1 device == 1 proc × 2 devices, bit for bit: {same}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
