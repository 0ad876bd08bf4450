"""What the disk cache keeps, and what it saves: every kind of call of
`tests/cache_worker.py` run in a fresh process with an empty cache folder, then in a
second fresh process on the same folder (first call and later-process call, seconds
of the call itself, import excluded), and whether the cache kept its programs.

    python benchmarks/cache.py [--core 1] [CASE ...]

(`--worker OUT.npz CASE`: one such process, the worker's run with its calls timed.)

Writes `benchmarks/results/cache.json` (every case), or `cache_subset.json` where
CASE names some: a partial run never overwrites the table of a full one.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time


HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
import cache_worker  # noqa: E402


def run(cache, out, case, core):
    env = dict(os.environ, LAGRAX_CACHE_DIR=cache)
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", out, case]
    if core is not None:
        cmd = ["taskset", "-c", str(core), *cmd]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"exit": proc.returncode}
    with open(out.removesuffix(".npz") + ".json") as fh:
        return json.load(fh)[case]


def timed(call):
    """The worker's run: the call and its seconds (import excluded)."""
    import jax

    start = time.perf_counter()
    result = jax.block_until_ready(call())
    return result, {"seconds": time.perf_counter() - start}


def main():
    if sys.argv[1:2] == ["--worker"]:
        return cache_worker.main(sys.argv[2], sys.argv[3:], run=timed)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("cases", nargs="*", default=cache_worker.CASES)
    p.add_argument("--core", type=int, default=None, help="pin to this core")
    args = p.parse_args()
    rows = {}
    print(f"{'call':32s} {'kept':>5s} {'first':>8s} {'later':>8s}")
    for case in args.cases:
        with tempfile.TemporaryDirectory() as tmp:
            cache = os.path.join(tmp, "cache")
            first = run(cache, os.path.join(tmp, "1.npz"), case, args.core)
            later = run(cache, os.path.join(tmp, "2.npz"), case, args.core)
        kept = later.get("loaded", 0) > 0 and later.get("compiled", 0) == 0
        rows[case] = {"first": first, "later": later, "kept": kept}
        f = first.get("seconds", float("nan"))
        s = later.get("seconds", float("nan"))
        note = "" if "exit" not in later else f" exit {later['exit']}"
        print(f"{case:32s} {'yes' if kept else 'no':>5s} {f:8.2f} {s:8.2f}{note}")
    full = set(args.cases) >= set(cache_worker.CASES)
    out = os.path.join(HERE, "results", "cache.json" if full else "cache_subset.json")
    with open(out, "w") as fh:
        json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
