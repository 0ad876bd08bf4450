r"""Periods of oscillation by integration to the turning points, one or many at once.

A one-degree-of-freedom system released from rest at $q_0$ moves until its velocity
vanishes again at the next turning point $q_1$, then comes back. The period is the time
to return to $q_0$:

$$T = t(q_0 \to q_1) + t(q_1 \to q_0).$$

When $L$ is even in $\dot q$ and has no explicit time dependence (every natural system
$L = \frac12 m(q)\dot q^2 - V(q)$, symmetric potential or not) the return leg is the
time-reversed outgoing leg, so $T = 2\,t(q_0 \to q_1)$: half the work. Nothing here
assumes a centre of oscillation; the turning points are found wherever they are.

Numerical choices (each one a measured trap):

- Each lane is integrated in its own units, $x = q/|q_0|$ and $s = t/\tau$ with
  $\tau = \sqrt{|q_0| / |\ddot q(q_0)|}$, so that `rtol`/`atol` mean the same thing at
  an amplitude of $10^{-3}$ as at $3$ (small amplitudes keep their relative accuracy).
- The turning point is detected by a sign change of $\sigma\dot q$ ($\sigma$ the sign of
  the acceleration at the start of the leg) with a *direction*, so that the exact zero
  at release does not fire the event.
- It is located without a root finder on the dense output: from the state at the end of
  the step that crossed it, the solve switches its independent variable to $\dot q$
  (Hénon's trick) and integrates $dt/d\dot q = 1/\ddot q$, $dq/d\dot q = \dot q/\ddot q$
  from $\dot q(t_e)$ to exactly $0$ with the same solver and tolerances: a Newton step
  made exact, with no iteration that can fail to converge and no interpolation error.
- A lane whose energy $h = \dot q\,\partial L/\partial\dot q - L$ at the turning point
  differs from its value at release by more than `energy_tol` (relative to the work
  scale $|M\ddot q|\,|q_0|$ at release) is a failure, whatever the solver said: a
  solve through a coordinate singularity can "succeed" with a garbage trajectory.
"""


import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ._checks import (
    as_real_array,
    check_choice,
    check_finite,
    check_instance,
    check_one_dof,
    is_concrete,
    positive_int,
    positive_scalar,
    tolerances,
)
from ._custom_types import Lagrangian, RealScalarLike
from ._mechanics import _accelerations, _jacobi
from ._results import (
    ENERGY_DRIFT,
    first_of,
    MAX_STEPS,
    NONFINITE_INPUT,
    NOT_OSCILLATING,
    ROOT_FIND_FAILED,
    SINGULAR_MASS,
    SOLVER_FAILED,
    STATUS_CODES as STATUS_CODES,
    status_message as status_message,
    status_result,
    SUCCESS,
)


# ------------------------------------------------------------------ one lane, traced

# |q - q0| beyond 1e6 max(|q0|, 1) means the motion is not a bounded oscillation. (Not
# 1e6 |q0|: released 1e-8 from the cycloid's cusp in θ, a normal swing is 1e8 |q0|.)
_ESCAPE = 1e6
_NO_LIMIT = 1e30


class _Lane(eqx.Module):
    """Outputs of one lane (stacked over lanes under vmap)."""

    period: Array
    status: Array
    steps: Array  # steps of every batched loop of the lane, shape (n_loops,)


_METHODS = ("matched", "half", "full", "quarter")
_REFINE_SUBSTEPS = 4


def _controller(rtol, atol, dtype):
    # In the lane's own units a step below ~1000 ulps of 1 carries no information:
    # a NaN vector field (singular mass matrix) stops fast with dt_min_reached.
    dtmin = 1024 * jnp.finfo(dtype).eps
    return dfx.PIDController(rtol=rtol, atol=atol, dtmin=dtmin, force_dtmin=False)


def _refine(solver, field, g, s, x, v, rtol, atol):
    r"""Hénon's trick: integrate from the event value $w_e = g(s, x, v)$ to $w = 0$
    with $w$ as the independent variable, $d(s, x, v)/dw = (1, \dot x, \ddot x)/\dot g$,
    in a fixed number of steps of `solver`. Returns the state at $w = 0$ and the largest
    scaled error estimate of those steps (above 1: not to tolerance)."""
    w0 = g(s, x, v)
    dtype = w0.dtype

    def henon(w, y, args):
        s, x, v = y
        xdot, vdot = field(s, (x, v), None)
        _, gdot = jax.jvp(g, (s, x, v), (jnp.ones((), dtype), xdot, vdot))
        return 1 / gdot, xdot / gdot, vdot / gdot

    term = dfx.ODETerm(henon)
    dw = -w0 / _REFINE_SUBSTEPS
    y = (s, x, v)
    state = solver.init(term, w0, w0 + dw, y, None)

    def body(i, carry):
        y, state, worst = carry
        wa = w0 + i * dw
        wb = jnp.where(i == _REFINE_SUBSTEPS - 1, 0.0, wa + dw)
        y1, err, _, state, _ = solver.step(term, wa, wb, y, None, state, False)
        scaled = [
            jnp.abs(e) / (atol + rtol * jnp.maximum(jnp.abs(a), jnp.abs(b)))
            for e, a, b in zip(err, y, y1)
        ]
        worst = jnp.maximum(worst, jnp.max(jnp.stack(scaled[1:])))
        return y1, state, worst

    y, _, worst = jax.lax.fori_loop(
        0, _REFINE_SUBSTEPS, body, (y, state, jnp.zeros((), dtype))
    )
    return y, worst


def _lane(L, q0, rtol, atol, t_max, energy_tol, *, solver, max_steps, method):
    r"""Period of one release point `q0` (a scalar). Pure, traceable, vmappable."""
    dtype = q0.dtype
    eps = jnp.finfo(dtype).eps
    zero = jnp.zeros((), dtype)
    finite_q0 = jnp.isfinite(q0)
    q0 = jnp.where(finite_q0, q0, 1.0)
    a0, (M0, ok0) = _accelerations(L, q0[None], zero[None], zero)
    a0, M0 = a0[0], M0[0, 0]
    start_ok = ok0 & jnp.isfinite(a0)
    moving = a0 != 0
    valid = finite_q0 & start_ok & moving
    # The lane's own units: lengths |q0| (1 if q0 = 0), times sqrt(|q0| / |q̈0|); and
    # the state is the displacement from the release point, x = (q - q0)/|q0|, so the
    # error control is relative to how far the motion has gone (near a release close to
    # an unstable equilibrium, errors relative to |q0| would swamp the slow departure).
    Qs = jnp.where(q0 != 0, jnp.abs(q0), 1.0)
    a0s = jnp.where(valid, a0, -1.0)
    tau = jnp.sqrt(Qs / jnp.abs(a0s))
    Vs = Qs / tau
    As = Qs / tau**2
    # No time limit by default: max_steps bounds the work, the escape event catches
    # runaways, and a local time scale says little about the period (released near the
    # cycloid's cusp in θ, tau is 1e-8 of it).
    s_end = jnp.asarray(_NO_LIMIT, dtype) if t_max is None else t_max / tau
    s_end = jnp.where(valid, s_end, 0.0)
    sigma = jnp.sign(a0s)
    escape = _ESCAPE * jnp.maximum(Qs, 1.0) / Qs

    def accel(s, x, v):
        qddot, _ = _accelerations(L, (q0 + Qs * x)[None], (Vs * v)[None], tau * s)
        return qddot[0] / As

    def field(s, y, args):
        x, v = y
        return v, accel(s, x, v)

    def leg(s0, x_start, g):
        """From rest at x_start, time s0, until g(s, x, v) goes from + to <= 0."""
        event = dfx.Event(
            (
                lambda s, y, args, **kw: g(s, *y),
                lambda s, y, args, **kw: jnp.abs(y[0]) > escape,
            ),
            direction=(False, None),
        )
        sol = dfx.diffeqsolve(
            dfx.ODETerm(field),
            solver,
            s0,
            jnp.maximum(s_end, s0),
            None,
            (x_start, zero),
            stepsize_controller=_controller(rtol, atol, dtype),
            max_steps=max_steps,
            event=event,
            throw=False,
        )
        s_e, x_e, v_e = sol.ts[-1], sol.ys[0][-1], sol.ys[1][-1]
        occurred = sol.result == dfx.RESULTS.event_occurred
        hit = occurred & sol.event_mask[0]
        escaped = occurred & sol.event_mask[1]
        ran_out = sol.result == dfx.RESULTS.successful  # reached s_end, no event
        good = hit & jnp.isfinite(s_e) & jnp.isfinite(x_e) & jnp.isfinite(v_e)
        # Where the event did not fire, refine a harmless copy of the start instead.
        s_e, x_e, v_e = (
            jnp.where(good, a, b) for a, b in ((s_e, s0), (x_e, x_start), (v_e, zero))
        )
        (s1, x1, v1), worst = _refine(solver, field, g, s_e, x_e, v_e, rtol, atol)
        a1 = accel(s1, x1, v1)
        refined = (
            jnp.isfinite(s1)
            & jnp.isfinite(x1)
            & jnp.isfinite(v1)
            & jnp.isfinite(a1)
            & (worst <= 10.0)
        )
        status = first_of(
            (good & refined, SUCCESS),
            (good, ROOT_FIND_FAILED),
            (escaped | ran_out, NOT_OSCILLATING),
            (sol.result == dfx.RESULTS.max_steps_reached, MAX_STEPS),
            default=SOLVER_FAILED,
        )
        stop = (
            jnp.where(good, s1, sol.ts[-1]),
            jnp.where(good, x1, sol.ys[0][-1]),
            jnp.where(good, v1, sol.ys[1][-1]),
        )
        steps = jnp.stack([sol.stats["num_steps"], jnp.asarray(_REFINE_SUBSTEPS)])
        return stop, a1, status, steps

    if method == "quarter":
        # Point of maximum speed, q̈ = 0 (the bottom of a mirror-symmetric well).
        (s_q, x_q, v_q), _, status, steps = leg(
            zero, zero, lambda s, x, v: sigma * accel(s, x, v)
        )
        s_total = 4 * s_q
        end = (s_q, x_q, v_q)
    else:
        end, a1, status, steps = leg(zero, zero, lambda s, x, v: sigma * v)
        s_total = 2 * end[0]
        if method == "full":
            ok1 = status == SUCCESS
            sigma2 = jnp.where(ok1, jnp.sign(a1), -sigma)
            end, _, status2, steps2 = leg(
                jnp.where(ok1, end[0], zero),
                jnp.where(ok1, end[1], zero),
                lambda s, x, v: sigma2 * v,
            )
            status = jnp.where(ok1, status2, status)
            s_total = end[0]
            steps = jnp.concatenate([steps, steps2])
    s_last, x_end, v_end = end

    # Energy check where the solve stopped (normally a turning point).
    q_end, qdot_end, t_end = q0 + Qs * x_end, Vs * v_end, tau * s_last
    h0, size0 = _jacobi(L, q0[None], zero[None], zero)
    h1, size1 = _jacobi(L, q_end[None], qdot_end[None], t_end)
    scale = jnp.abs(M0 * a0s) * Qs
    drift = jnp.abs(h1 - h0)
    tol = jnp.sqrt(rtol) if energy_tol is None else energy_tol
    allowed = tol * scale + 1024 * eps * (size0 + size1)
    drifted = ~(drift <= allowed)  # NaN energies count as drift
    # A singular or indefinite mass matrix where the solve stopped?
    _, (_, ok_end) = _accelerations(L, q_end[None], qdot_end[None], t_end)
    status = jnp.where(
        (status == SUCCESS) & drifted,
        ENERGY_DRIFT,
        jnp.where(
            (status != SUCCESS) & (status != NOT_OSCILLATING) & ~ok_end,
            SINGULAR_MASS,
            jnp.where(
                (status == NOT_OSCILLATING) & drifted & jnp.isfinite(h1),
                ENERGY_DRIFT,
                status,
            ),
        ),
    )
    status = first_of(
        (~finite_q0, NONFINITE_INPUT),
        (~start_ok, SINGULAR_MASS),
        (~moving, NOT_OSCILLATING),
        default=status,
    )
    T = jnp.where(status == SUCCESS, tau * s_total, jnp.nan)
    return _Lane(T, status.astype(jnp.int32), steps.astype(jnp.int32))


class _NoPeriodError(ValueError, RuntimeError):
    # No period at this release point: a bad `q0` (ValueError), and a failed status
    # like the others `period` raises as RuntimeError.
    pass


def _check_options(L, dtype, solver, rtol, atol, t_max, energy_tol, max_steps, method):
    """The checks `period` and `sweep_periods` share, run once per call."""
    check_one_dof(L, dtype)
    check_instance(
        solver,
        "solver",
        dfx.AbstractAdaptiveSolver,
        "an adaptive diffrax solver (the turning point is found with adaptive steps), "
        "e.g. diffrax.Dopri8()",
    )
    rtol, atol = tolerances(rtol, atol, dtype, stacklevel=3)
    t_max = positive_scalar(t_max, "t_max", dtype, optional=True)
    energy_tol = positive_scalar(energy_tol, "energy_tol", dtype, optional=True)
    max_steps = positive_int(max_steps, "max_steps")
    return (
        rtol,
        atol,
        t_max,
        energy_tol,
        max_steps,
        check_choice(method, "method", _METHODS),
    )


# ---------------------------------------------------------------------------- period


def period(
    L: Lagrangian,
    q0: RealScalarLike,
    *,
    solver: dfx.AbstractAdaptiveSolver = dfx.Dopri8(),
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
        Newton. Right whenever `"half"` is (below), and nothing is integrated through
        the bottom of the swing, where one rounding of $\dot q$ is an energy error
        that the slow approach to a hump amplifies: 2.7e-13 on the pendulum at
        $\pi - 10^{-3}$ where `"half"` loses 1.7e-9. What remains there is the
        rounding of $L(q, 0)$ itself, which leaves $q_1$ undetermined within a band
        that the error estimate accounts for.
    - `"half"`: $T = 2\,t(q_0 \to q_1)$. Exact when $L$ is even in $\dot q$
        and has no explicit time dependence (every $L = \frac12 m(q)\dot q^2 - V(q)$,
        symmetric potential or not): the return leg is the outgoing one reversed.
    - `"full"`: through $q_1$ and back to $q_0$: any autonomous one-coordinate $L$;
        twice the work.
    - `"quarter"`: $T = 4\,t(q_0 \to q_m)$, $q_m$ the point of maximum speed
        ($\ddot q = 0$, found by event, not assumed). Exact only for a well that is
        mirror-symmetric about $q_m$ (pendulum, cycloid); half the work of `"half"`,
        and the only well-conditioned choice near a separatrix: past the bottom, one
        rounding of $\dot q$ changes $T$ by $\sim 4\,\delta E/\delta^2$ for a release
        $\delta$ below a hump (pendulum: ~1e-10 relative at $\pi - 10^{-3}$ in float64,
        whatever the tolerances), which `"quarter"` never integrates through. A lane
        whose mirror image of $q_0$ is not a turning point gets status
        `not_symmetric` instead of a wrong number.

    With an explicit Runge–Kutta solver (every diffrax ERK) this runs on the same
    kernel as `sweep_periods`, and gives the same numbers; other solvers go through
    `diffrax.diffeqsolve` (there `"matched"` is not available and `"half"` is used).

    Plain JAX: works under `jit`, `vmap` and `grad` (with respect to `q0` and to any
    parameter `L` closes over). For many amplitudes at once use `sweep_periods`.

    **Arguments:**

    - `L`: the Lagrangian `L(q, qdot, t) -> scalar` of one coordinate (`q` has shape
        `(1,)`).
    - `q0`: the release point (the amplitude, in the coordinate `L` is written in), a
        scalar or shape `(1,)`.
    - `solver`: an adaptive diffrax solver (default `Dopri8()`).
    - `rtol`, `atol`: tolerances, in the lane's own units (lengths in $|q_0|$, times
        in $\sqrt{|q_0|/|\ddot q(q_0)|}$): small amplitudes keep relative accuracy.
    - `max_steps`: the most steps for one swing.
    - `t_max`: give up (status `not_oscillating`) if no turning point by then; default
        no limit (`max_steps` bounds the work; a coordinate running away to
        $|q - q_0| > 10^6 \max(|q_0|, 1)$ stops the solve as not oscillating).
    - `energy_tol`: the largest accepted energy drift between release and turning point,
        relative to $|M\ddot q|\,|q_0|$ at release; default $\sqrt{\text{rtol}}$.
    - `method`: `"matched"`, `"half"`, `"full"` or `"quarter"`, see above.
    - `throw`: raise on failure (under `jit`/`vmap` an equinox runtime error); with
        `throw=False` a failure gives NaN.
    - `error_estimate`: also return an estimate of $|T - T_\text{exact}|/T$ (see
        `sweep_periods`; it costs a second solve at looser tolerances), and report a
        lane whose estimate exceeds 100 rtol as `tolerance_not_met`.

    **Returns:**

    $T$, a scalar; `(T, estimate)` with `error_estimate=True`.

    **Raises:**

    - `TypeError`/`ValueError`: bad arguments (the message names the argument).
    - `ValueError` (eager): `q0` is not finite, or L does not oscillate from it
        (status `not_oscillating`, `singular_mass`; the error is also a
        `RuntimeError`).
    - `RuntimeError` (eager) or an equinox runtime error (traced), with the status
        message (see `status_message`), when the period cannot be trusted.

    **Example:**

    ```python
    L = lagrax.systems.pendulum.lagrangian()
    lagrax.period(L, 1.0)  # 6.6986..., = pendulum_period(1.0)
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
    rtol, atol, t_max, energy_tol, max_steps, method = _check_options(
        L, q0.dtype, solver, rtol, atol, t_max, energy_tol, max_steps, method
    )
    from ._sweep import explicit_tableau, one_lane

    tab = explicit_tableau(solver)
    if tab is None:  # an implicit solver: diffeqsolve, and "half" for "matched"
        out = _lane(
            L,
            q0,
            rtol,
            atol,
            t_max,
            energy_tol,
            solver=solver,
            max_steps=max_steps,
            method="half" if method == "matched" else method,
        )
        estimate = jnp.full_like(out.period, jnp.nan)
    else:
        T, status, estimate = one_lane(
            L, q0, tab, method, max_steps, rtol, atol, t_max, energy_tol, error_estimate
        )
        out = _Lane(T, status, jnp.zeros((1,), jnp.int32))
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
            out = status_result(out.status).error_if(out, out.status != SUCCESS)
    return (out.period, estimate) if error_estimate else out.period


# ---------------------------------------------------------------------------- sweep
