"""What `lagrax sweep` shows and writes: the table, the .csv or .npz, the progress."""

import functools
import sys

from .checkpoint import atomic_write


def status_name(code):
    import lagrax

    names = getattr(lagrax, "STATUS_CODES", None)
    if isinstance(names, dict) and code in names:
        name = names[code]
        return name if isinstance(name, str) else str(name[0])
    return "success" if code == 0 else f"status_{code}"


_REFERENCE_WORDS = {
    "exact": "the exact period",
    "quadrature": "lagrax.quadrature_period",
    "none": "no reference",
}


def table(results, rows):
    import numpy as np

    estimates = any("error_estimate" in r for r in results)
    normalized = any(r["target"].T0 for r in results)
    width = max(9, *(len(r["system"]) for r in results))
    head = (
        f"{'system':<{width}} {'amplitude':>10} {'period':>18} "
        + (f"{'T/T0':>12} " if normalized else "")
        + f"{'reference':>18} {'rel. error':>10}"
    )
    if estimates:
        head += f" {'estimate':>9}"
    lines = [head + "  status"]
    for r in results:
        n = len(r["amplitude"])
        picks = sorted(set(np.linspace(0, n - 1, min(rows, n)).round().astype(int)))
        for i in picks:
            code = int(r["status"][i])
            line = (
                f"{r['system']:<{width}} {r['amplitude'][i]:>10.6f} "
                f"{r['period'][i]:>18.15f} "
                + (f"{r['T_over_T0'][i]:>12.9f} " if normalized else "")
                + f"{r['reference'][i]:>18.15f} {r['rel_error'][i]:>10.1e}"
            )
            if estimates:
                est = r.get("error_estimate", np.full(n, np.nan))[i]
                line += f" {est:>9.1e}"
            lines.append(line + f"  {status_name(code)}")
    lines.append("")
    for r in results:
        ok = r["status"] == 0
        kind = r["reference_kind"]
        if kind == "none":
            accuracy = "no reference (--reference quadrature compares)"
        else:
            compared = ok & np.isfinite(r["rel_error"])
            worst = float(np.max(r["rel_error"][compared])) if compared.any() else None
            accuracy = "max relative error " + (
                f"{worst:.1e}" if worst is not None else "n/a"
            )
            accuracy += f" vs {_REFERENCE_WORDS[kind]}"
            missing = int((ok & ~np.isfinite(r["reference"])).sum())
            if missing:
                accuracy += f" ({missing} without a reference value)"
        if "error_estimate" in r and ok.any():
            accuracy += f", max error estimate {np.nanmax(r['error_estimate'][ok]):.1e}"
        lines.append(
            f"{r['system']}: {len(ok)} amplitudes"
            + (f" ({r['solver']})" if r.get("solver") else "")
            + f", {int((~ok).sum())} failed, "
            f"{accuracy}, {r['seconds']:.2f} s (compile included), useful lane-steps "
            f"{r['useful_fraction']:.0%}"
        )
    return "\n".join(lines)


_COLUMNS = ("amplitude", "q0", "period", "T_over_T0", "reference", "rel_error")


def write_out(path, results):
    import csv

    import numpy as np

    estimates = all("error_estimate" in r for r in results)
    columns = (*_COLUMNS, "error_estimate") if estimates else _COLUMNS
    if not any(r["target"].T0 for r in results):  # no T₀ known: no column of NaN
        columns = tuple(c for c in columns if c != "T_over_T0")
    if path.lower().endswith(".npz"):
        data = {
            "system": np.concatenate(
                [np.full(len(r["amplitude"]), r["system"]) for r in results]
            ),
            "reference_kind": np.concatenate(
                [np.full(len(r["amplitude"]), r["reference_kind"]) for r in results]
            ),
        }
        for c in (*columns, "status", "steps"):
            data[c] = np.concatenate([r[c] for r in results])
        atomic_write(path, lambda p: np.savez(p, **data))
        return

    def write(p):
        with open(p, "w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(
                ["system", *columns, "status", "status_name", "steps", "reference_kind"]
            )
            for r in results:
                for i in range(len(r["amplitude"])):
                    code = int(r["status"][i])
                    w.writerow(
                        [
                            r["system"],
                            *(repr(float(r[c][i])) for c in columns),
                            code,
                            status_name(code),
                            int(r["steps"][i]),
                            r["reference_kind"],
                        ]
                    )

    atomic_write(path, write)


class Bar:
    """tqdm over one system's amplitudes: done, periods/s, time left. Silent when
    quiet, on processes other than 0, or when stderr is not a terminal."""

    def __init__(self, name, total, enabled):
        self.bar = None
        if enabled:
            from tqdm.auto import tqdm

            self.bar = tqdm(
                total=total,
                desc=name,
                unit=" periods",
                file=sys.stderr,
                disable=None,  # None: off when stderr is not a terminal
                dynamic_ncols=True,
                smoothing=0.1,
            )
            if self.bar.disable:
                self.bar = None

    @property
    def active(self):
        return self.bar is not None

    def to(self, n):
        if self.bar is not None and n > self.bar.n:
            self.bar.update(n - self.bar.n)

    def close(self):
        if self.bar is not None:
            self.bar.close()


def bar_meter(bar, offset, count):
    """A diffrax progress meter for `sweep_periods` that moves `bar` to `offset`
    plus the done fraction of `count` amplitudes."""
    return _bar_meter_class()(bar, offset, count)


@functools.cache
def _bar_meter_class():
    import diffrax as dfx
    import equinox as eqx

    class BarMeter(dfx.AbstractProgressMeter):
        bar: Bar = eqx.field(static=True)
        offset: int = eqx.field(static=True)
        count: int = eqx.field(static=True)

        def init(self):
            return None

        def step(self, state, progress):
            self.bar.to(self.offset + round(float(progress) * self.count))
            return state

        def close(self, state):
            pass

    return BarMeter
