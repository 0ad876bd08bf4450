"""`lagrax sweep`: each target swept in checkpointed blocks, then the outputs."""

import sys
import time

from . import targets as _targets
from .chart import plot
from .checkpoint import Blocks, DamagedPiece
from .output import Bar, bar_meter, status_name, table, write_out
from .parser import check_paths, UsageError
from .processes import broadcast, setup_jax


_QUADRATURE_BLOCK = 2048  # release points per quadrature call (bounded memory)


def sweep(target, args, devices, blocks, targets, bar):
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
                try:
                    part = blocks.load(target, b)
                except DamagedPiece as e:
                    part = e
                if not isinstance(part, dict):  # verified at the start: changed since
                    raise UsageError(
                        f"checkpoint {blocks.path(target, b)} changed during the run"
                        + (f" ({part})" if part is not None else "")
                        + "; run the command again"
                    )
        else:
            meter = bar_meter(bar, sl.start, sl.stop - sl.start)
            res = lagrax.sweep_periods(
                target.L,
                jnp.asarray(q0[sl]),
                solver=solver,
                rtol=args.rtol,
                atol=args.atol,
                method=target.method,
                lanes=blocks.lanes,
                devices=devices,
                progress_meter=meter if bar.active else dfx.NoProgressMeter(),
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
                blocks.save(target, b, part)
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
    add_reference(r, target, args)
    return r


def add_reference(r, target, args):
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


def run_sweep(args):
    import jax
    import numpy as np

    devices = setup_jax(args)
    targets = _targets.targets(args)
    if len({id(t.L) for t in targets}) > 1:
        from .._period import tier

        # One compact program for every system, not a specialized compile each.
        tier.several_lagrangians()
    writer = jax.process_index() == 0
    if args.distributed:
        # Only process 0 writes, so only its view of the paths counts; the others
        # learn the verdict and stop with it.
        error = None
        if writer:
            try:
                check_paths(args)
            except UsageError as e:
                error = e
        if int(broadcast(np.int64(error is not None))):
            raise error or UsageError("process 0 cannot write --out/--plot")
    blocks = Blocks(args, targets, devices)
    if writer and blocks.resumed and not args.quiet:
        total = sum(blocks.n_blocks.values())
        print(
            f"lagrax: resuming from {blocks.dir}: {blocks.resumed} of {total} blocks "
            "already done",
            file=sys.stderr,
        )
    results = []
    for t in targets:
        bar = Bar(t.name, args.count, writer and not args.quiet)
        try:
            results.append(sweep(t, args, devices, blocks, targets, bar))
        finally:
            bar.close()
    failed = 0
    if writer:
        print(table(results, args.rows))
        if args.out is not None:
            import shutil

            write_out(args.out, results)
            shutil.rmtree(blocks.dir, ignore_errors=True)
            print(f"wrote {args.out}")
        if args.plot is not None:
            plot(args.plot, results, args.rtol)
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
                    f"{n} × {status_name(int(c))} ({lagrax.status_message(int(c))})"
                    for c, n in zip(codes, counts)
                ),
                file=sys.stderr,
            )
    # Every process leaves with process 0's verdict.
    failed = int(broadcast(np.int64(failed)))
    return 1 if failed else 0
