r"""Periods of oscillation by integration to the turning points, one or many at once.

A one-degree-of-freedom system released from rest at $q_0$ moves until its velocity
vanishes again at the next turning point $q_1$, then comes back. The period is the time
to return to $q_0$:

$$T = t(q_0 \to q_1) + t(q_1 \to q_0).$$

When $L$ is even in $\dot q$ and has no explicit time dependence (every natural system
$L = \frac12 m(q)\dot q^2 - V(q)$, symmetric potential or not) the return leg is the
time-reversed outgoing leg, so $T = 2\,t(q_0 \to q_1)$: half the work. Nothing here
assumes a centre of oscillation; the turning points are found wherever they are.

`period` is the one-lane entry point: it checks its arguments, runs one lane of the
period kernel (`loop.py`: the loop over lanes; `methods.py`: legs; `estimate.py`:
the error estimate; `finish.py`: statuses) and turns a failed status into an error.
Numerical choices (each one a trap met in practice):

- Each lane is integrated in its own units, $x = (q - q_0)/|q_0|$ and $s = t/\tau$
  with $\tau = \sqrt{|q_0| / |\ddot q(q_0)|}$, so that `rtol`/`atol` mean the same
  thing at an amplitude of $10^{-3}$ as at $3$.
- An event (turning point, point of maximum speed, a given position) is detected by a
  sign change over an accepted step, with a direction, so that the exact zero at
  release does not fire it. A Taylor step locates it inside the step from its
  polynomials (the solution over the whole step); a Runge–Kutta step by trial steps
  from the last accepted state with the step length as the unknown (Newton, or a
  secant for $\ddot q = 0$): each trial is a full step of the solver, nothing is
  interpolated.
- A lane whose energy $h = \dot q\,\partial L/\partial\dot q - L$ at the end of a
  leg differs from its value at release by more than `energy_tol` (relative to the
  work scale $|M\ddot q|\,|q_0|$ at release) is a failure, whatever the solver said:
  a solve through a coordinate singularity can "succeed" with a garbage trajectory.
"""

import diffrax as dfx
import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array

from .._checks import as_real_array, check_finite, is_concrete
from .._custom_types import Lagrangian, RealScalarLike
from .._results import (
    NONFINITE_INPUT,
    NOT_OSCILLATING,
    SINGULAR_MASS,
    STATUS_CODES as STATUS_CODES,
    status_member,
    status_message as status_message,
    SUCCESS,
)
from .._taylor.taylor import Taylor
from .methods import Method
from .options import check_options
from .solver import canonical_inputs, stepper_of
from .sweep import _eager, _sweep_call


class _Lane(eqx.Module):
    period: Array
    status: Array


class _NoPeriodError(ValueError, RuntimeError):
    # No period at this release point: a bad `q0` (ValueError), and a failed status
    # like the others `period` raises as RuntimeError.
    pass


def period(
    L: Lagrangian,
    q0: RealScalarLike,
    *,
    solver: "dfx.AbstractAdaptiveSolver | Taylor" = dfx.Dopri8(),
    rtol: RealScalarLike = 1e-13,
    atol: RealScalarLike = 1e-13,
    max_steps: int = 4096,
    t_max: RealScalarLike | None = None,
    energy_tol: RealScalarLike | None = None,
    method: str = "matched",
    throw: bool = True,
    error_estimate: bool = False,
) -> Array | tuple[Array, Array]:
    r"""The period of a one-degree-of-freedom oscillation released from rest at `q0`.

    $$T = t(q_0 \to q_1) + t(q_1 \to q_0),$$

    with $q_1$ the next turning point ($\dot q = 0$) after release, found wherever it is
    (asymmetric potentials included: no centre of oscillation is assumed). `method`
    says how much of the orbit is integrated:

    - `"matched"` (default): $T = 2\,(t(q_0 \to q_m) + t(q_1 \to q_m))$, two legs
        each started at rest at its own turning point and ended at the point of
        maximum speed $q_m$ ($\ddot q = 0$, found by event), the far turning point
        $q_1$ solved from $L(q_1, 0) = L(q_0, 0)$ (the energy at rest) by bracketed
        Newton. Right whenever `"half"` is, and nothing is integrated through the
        bottom of the swing, where one rounding of $\dot q$ is an energy error that
        the slow approach to a hump amplifies (near a separatrix `"half"` loses
        digits that `"matched"` keeps). What remains is the rounding of $L(q, 0)$
        itself, which leaves $q_1$ undetermined within a band that the error
        estimate accounts for.
    - `"half"`: $T = 2\,t(q_0 \to q_1)$. Exact when $L$ is even in $\dot q$
        and has no explicit time dependence (every $L = \frac12 m(q)\dot q^2 - V(q)$,
        symmetric potential or not): the return leg is the outgoing one reversed.
    - `"full"`: through $q_1$ and back to $q_0$: any autonomous one-coordinate $L$;
        twice the work.
    - `"quarter"`: $T = 4\,t(q_0 \to q_m)$. Exact only for a well that is
        mirror-symmetric about $q_m$ (pendulum, cycloid); half the work of `"half"`,
        and never integrates past the bottom, whose rounding error grows as
        $\sim 4\,\delta E/\delta^2$ for a release $\delta$ below a hump. A lane whose
        mirror image of $q_0$ is not a turning point, or whose $L$ is not
        mirror-symmetric about $q_m$ at three sample points across the swing, gets
        status `not_symmetric` instead of a wrong number (sampled, not proven: an
        asymmetry confined between the samples is missed).

    This runs on the kernel of `sweep_periods` (one lane) and gives the same numbers
    for the same solver. Plain JAX: works under `jit`, `vmap` and `grad` (with
    respect to `q0` and to any parameter `L` closes over). For many amplitudes at
    once use `sweep_periods`.

    **Arguments:**

    - `L`: the Lagrangian `L(q, qdot, t) -> scalar` of one coordinate (`q` has shape
        `(1,)`).
    - `q0`: the release point (the amplitude, in the coordinate `L` is written in), a
        scalar or shape `(1,)`.
    - `solver`: an adaptive explicit Runge–Kutta diffrax solver, whose tableau the
        kernel steps through (default `Dopri8()`; `Tsit5()`, `Dopri5()`, … work
        too), or `lagrax.Taylor()` (also `Taylor(fallback=Dopri8())`, the default
        of `sweep_periods`). The defaults differ on purpose: one lane runs in
        milliseconds either way, so the first call's compile decides, and `Dopri8()`
        compiles faster than `Taylor()` (its first `jax.grad` several times
        faster); a sweep runs long enough for the Taylor step's speed to pay.
    - `rtol`, `atol`: tolerances, in the lane's own units (lengths in $|q_0|$, times
        in $\sqrt{|q_0|/|\ddot q(q_0)|}$): small amplitudes keep relative accuracy.
    - `max_steps`: the most steps for one swing.
    - `t_max`: give up (status `not_oscillating`) if no turning point by then; default
        no limit (`max_steps` bounds the work; a coordinate running away to
        $|q - q_0| > 10^6 \max(|q_0|, 1)$ stops the solve as not oscillating).
    - `energy_tol`: the largest accepted energy drift between release and turning
        point, relative to $|M\ddot q|\,|q_0|$ at release; default
        $\sqrt{\text{rtol}}$.
    - `method`: `"matched"`, `"half"`, `"full"` or `"quarter"`, see above.
    - `throw`: raise on failure (under `jit`/`vmap` an equinox runtime error); with
        `throw=False` a failure gives NaN.
    - `error_estimate`: also return an estimate of $|T - T_\text{exact}|/T$ (as
        `sweep_periods` computes it), and fail a lane whose estimate exceeds 100 rtol
        (`tolerance_not_met`). Off by default here, on in `sweep_periods`: here it
        changes what is returned (a pair instead of $T$), there it is one more field.

    **Returns:** $T$, a scalar; `(T, estimate)` with `error_estimate=True`.

    **Raises:**

    - `TypeError`/`ValueError`: bad arguments (the message names the argument).
    - `ValueError` (eager): `q0` is not finite, or L does not oscillate from it
        (status `not_oscillating`, `singular_mass`; the error is also a
        `RuntimeError`).
    - `RuntimeError` (eager) or an equinox runtime error (traced), with the status
        message (`lagrax.PeriodStatus`), when the period cannot be trusted.

    **Example:**

    ```python
    L = lagrax.systems.pendulum.lagrangian()
    lagrax.period(L, 1.0)  # 6.69997566..., = lagrax.systems.pendulum.period(1.0)
    ```
    """
    q0 = as_real_array(q0, "q0")
    if q0.shape not in ((), (1,)):
        raise ValueError(
            "`q0` must be a scalar or shape (1,): `period` is for one degree of "
            f"freedom; got shape {q0.shape}. For many amplitudes use sweep_periods."
        )
    q0 = q0.reshape(())
    if throw:
        check_finite(q0, "q0")
    opts = check_options(
        L, q0.dtype, solver, rtol, atol, t_max, energy_tol, max_steps, method
    )
    L_c, consts, solver = canonical_inputs(L, solver, q0.dtype)
    T, status, estimate = _one_lane(
        L_c, consts, q0, stepper_of(solver), opts, error_estimate
    )
    out = _Lane(T, status)
    if throw:
        if is_concrete(out.status):
            code = int(out.status)
            if code in (NOT_OSCILLATING, SINGULAR_MASS, NONFINITE_INPUT):
                raise _NoPeriodError(
                    "`q0` must be a release point from which L oscillates; got "
                    f"q0={float(q0)!r}: status {code} ({STATUS_CODES[code]}): "
                    f"{status_message(code)}."
                )
            if code != SUCCESS:
                raise RuntimeError(
                    f"lagrax.period failed for q0={float(q0)!r}: status {code} "
                    f"({STATUS_CODES[code]}): {status_message(code)}."
                )
        else:  # the status's own message, under jit too
            out = status_member(out.status).error_if(out, out.status != SUCCESS)
    return (out.period, estimate) if error_estimate else out.period


def _one_lane(L_c, consts, q0, stepper, opts, estimate):
    """`period` on the kernel: one release point (a scalar), one lane, the default
    device, for the canonical `L_c` and its constants. Returns `(T, status,
    error_estimate)` as scalars."""
    cfg = Method(stepper, opts.method, 1, opts.max_steps, bool(estimate))
    device = (jax.devices()[0],)
    args = (consts, opts.rtol, opts.atol, opts.t_max, opts.energy_tol)
    # As `sweep_periods`: one compiled call, whose forward-mode derivative is a
    # compiled program too, reused by every later eager `jax.grad`; eagerly through
    # the tiers and the library's disk cache of executables, and on the host
    # around it (op-by-op jnp compiles each operation on its first call).
    order = np.zeros((1,), np.int32)
    if is_concrete(q0, args):
        out, _ = _eager(L_c, cfg, device, np.reshape(np.asarray(q0), (1,)), order, args)
        first = lambda x: jax.device_put(np.asarray(x)[0])
        return first(out.periods), first(out.status), first(out.estimate)
    out, _ = _sweep_call(L_c, cfg, device, q0[None], order, *args)
    return out.periods[0], out.status[0], out.estimate[0]
