from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class SweepSpec:
    r"""What `lagrax sweep NAME` needs to know of a built-in system beyond its
    `lagrangian`, `period` and `small_amplitude_period`.

    A system module declares one as its `SWEEP`; one without it is swept with the
    defaults below (the amplitude is the release point $q_0$, the range is given with
    `--min`/`--max`).

    **Fields:**

    - `description`: what the system is, in a few words (the chart's legend).
    - `amplitude`: the amplitude's symbol and unit, e.g. `"θ₀ (rad)"`.
    - `amplitudes`: the default `(min, max)` of the amplitudes, or a function of the
        system's parameters (keywords) returning it, or `None` if there is none.
    - `bounds`: `(lo, hi)` with `lo < amplitude <= hi` required, or `None`.
    - `method`: the `method` of `lagrax.sweep_periods` to sweep with.
    - `lagrangian`: the factory of the Lagrangian that is integrated, where it is not
        the module's `lagrangian` (another coordinate, regular where that one is not).
    - `release_point`: amplitude -> release point $q_0$ in that Lagrangian's
        coordinate (NumPy arrays in and out), where they differ.
    - `default`: swept by `lagrax sweep` without a TARGET.
    """

    description: str
    amplitude: str = "q₀"
    amplitudes: tuple[float, float] | Callable[..., tuple | None] | None = None
    bounds: tuple[float, float] | None = None
    method: str = "matched"
    lagrangian: Callable | None = None
    release_point: Callable | None = None
    default: bool = False
