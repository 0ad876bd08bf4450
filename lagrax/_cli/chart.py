"""The chart of `lagrax sweep --plot`: T/T₀ against amplitude, the errors below."""

import os

from .checkpoint import atomic_write


def label(r):
    t = r["target"]
    return f"{t.description or t.name} (amplitude {t.amplitude_label})"


def chart(results, rtol):
    """The figure: T/T₀ (or T) against amplitude, and the relative error below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib import ticker

    from .._period.estimate import PROMISE

    fig, (top, bottom) = plt.subplots(
        2,
        1,
        figsize=(9.0, 6.4),
        sharex=True,
        gridspec_kw={"height_ratios": [3, 2]},
    )
    bottom.set_yscale("log")
    normalized = all(r["target"].T0 for r in results)
    floor = 1e-17
    any_failed = False
    for k, r in enumerate(results):
        color = f"C{k}"
        ok = r["status"] == 0
        y = r["T_over_T0"] if normalized else r["period"]
        top.plot(r["amplitude"][ok], y[ok], color=color, label=label(r))
        if (~ok).any():
            any_failed = True
            for ax in (top, bottom):
                ax.plot(
                    r["amplitude"][~ok],
                    np.full(int((~ok).sum()), 0.03),
                    "x",
                    color=color,
                    markersize=5,
                    transform=ax.get_xaxis_transform(),
                    label=f"failed: {int((~ok).sum())} ({r['system']})"
                    if ax is top
                    else None,
                )
        kind = r["reference_kind"]
        if kind != "none":
            err = r["rel_error"]
            shown = ok & np.isfinite(err)
            bottom.plot(
                r["amplitude"][shown],
                np.maximum(err[shown], floor),
                ".",
                color=color,
                markersize=2.5,
                label=f"{r['system']}: |T / T_ref − 1|, T_ref = {kind}",
            )
        if "error_estimate" in r:
            est = r["error_estimate"]
            shown = ok & np.isfinite(est)
            bottom.plot(
                r["amplitude"][shown],
                np.maximum(est[shown], floor),
                "-",
                color=color,
                alpha=0.6,
                linewidth=1,
                label=f"{r['system']}: error estimate",
            )
    # What decides: a lane whose estimate exceeds PROMISE rtol fails
    # (tolerance_not_met); a line at rtol itself would sit below every estimate.
    cutoff = PROMISE * rtol
    bottom.axhline(
        cutoff,
        color="0.4",
        linestyle=":",
        linewidth=1,
        label=f"cutoff {PROMISE:g} rtol = {cutoff:.0e}: an estimate above fails",
    )
    top.set_ylabel("T / T₀" if normalized else "period T")
    ys = [
        (r["T_over_T0"] if normalized else r["period"])[r["status"] == 0]
        for r in results
    ]
    ys = np.concatenate(ys) if ys else np.array([])
    ys = ys[np.isfinite(ys) & (ys > 0)]
    if ys.size and ys.max() / ys.min() > 30:
        top.set_yscale("log")
        # Plain numbers on every decade and between them, never "6×10⁰".
        top.yaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        top.yaxis.set_minor_formatter(ticker.NullFormatter())
    else:
        top.yaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
    top.set_title("Period against amplitude (lagrax sweep)")
    top.grid(True, which="both", alpha=0.3)
    # Legends beside the panels, never over the curves.
    outside = dict(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    top.legend(fontsize=8, **outside)
    shown = [
        line.get_ydata() for line in bottom.get_lines() if len(line.get_ydata()) > 1
    ]
    shown = np.concatenate(shown) if shown else np.array([cutoff])
    bottom.set_ylim(max(floor / 2, shown.min() / 4), max(cutoff, shown.max()) * 8)
    bottom.yaxis.set_major_locator(ticker.LogLocator(numticks=8))
    bottom.set_ylabel("relative error")
    bottom.set_xlabel("amplitude")
    bottom.grid(True, which="major", alpha=0.3)
    if bottom.get_legend_handles_labels()[0]:
        bottom.legend(fontsize=7, **outside)
    note = f"errors below {floor:.0e} drawn at it"
    if any_failed:
        note += "; × marks failed amplitudes"
    bottom.set_title(note, fontsize=8, loc="right")
    fig.tight_layout()
    return fig


def plot(path, results, rtol):
    import matplotlib.pyplot as plt

    fig = chart(results, rtol)
    ext = os.path.splitext(path)[1][1:]
    atomic_write(path, lambda p: fig.savefig(p, format=ext, dpi=120))
    plt.close(fig)
