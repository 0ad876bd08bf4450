"""From the loop's raw outcomes to statuses, event times and end states."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._results import (
    COORDINATE_SINGULARITY,
    ENERGY_DRIFT,
    MAX_STEPS as S_MAX_STEPS,
    NONFINITE_INPUT,
    NOT_OSCILLATING,
    ROOT_FIND_FAILED,
    SINGULAR_MASS,
    SOLVER_FAILED,
    SUCCESS,
)
from .._stepper.base import fused
from .estimate import BoundTerms
from .events import Event, MAX_SPEED
from .outcome import LOCATE_FAILED, LOCATED, MAX_STEPS, NO_EVENT
from .quantities import mechanics


class Ends(eqx.Module):
    """Each lane's status and where its leg ended (the event time carries the
    implicit-function tangent of the event)."""

    status: Int[Array, " n"]
    t_event: Float[Array, " n"]
    q_end: Float[Array, " n"]
    qdot_end: Float[Array, " n"]


def _status(raw, r, drifted, ok_end, h1):
    """The status from the raw outcome, the energy check and the release."""
    status = jnp.select(
        [raw == LOCATED, raw == LOCATE_FAILED, raw == NO_EVENT, raw == MAX_STEPS],
        [SUCCESS, ROOT_FIND_FAILED, NOT_OSCILLATING, S_MAX_STEPS],
        SOLVER_FAILED,
    )
    status = jnp.select(
        [
            (status == SUCCESS) & drifted,
            (status != SUCCESS) & (status != NOT_OSCILLATING) & ~ok_end,
            (status == NOT_OSCILLATING) & drifted & jnp.isfinite(h1),
        ],
        [ENERGY_DRIFT, SINGULAR_MASS, ENERGY_DRIFT],
        status,
    )
    return jnp.select(
        [~r.finite, ~r.start_ok, ~r.moving],
        [NONFINITE_INPUT, SINGULAR_MASS, NOT_OSCILLATING],
        status,
    )


def _lane_end(energy_tol, r, leg, target, kind, rtol, sigma, raw, s_e, x_e, v_e, *ss):
    """One lane: its status (a leg whose energy drifted beyond `energy_tol` fails,
    whatever the solver said), end state, the event function there and its jerk,
    and the error bound's sums in time units. `leg`: what `AutodiffMechanics.leg_end`
    gives."""
    dtype = r.q0.dtype
    eps = jnp.finfo(dtype).eps
    q0, M0, a0s, Qs, tau = r.q0, r.M0, r.a0s, r.Qs, r.tau
    q_end, qdot_end = q0 + Qs * x_e, (Qs / tau) * v_e
    (h0, size0), ((_, (M_end, ok_end)), (h1, size1)), a_e, jerk = leg
    scale = jnp.abs(M0 * a0s) * Qs
    tol = jnp.sqrt(rtol) if energy_tol is None else energy_tol
    allowed = tol * scale + 1024 * eps * (size0 + size1)
    drifted = ~(jnp.abs(h1 - h0) <= allowed)  # NaN energies count as drift
    # The estimate's sums in time units; they assume a constant mass, checked at the
    # leg's two ends.
    ph, J, F, G = ss
    const_mass = jnp.abs(M_end[0, 0] - M0) <= 8 * eps * jnp.abs(M0)
    terms = BoundTerms(
        tau * ph, tau * J, tau * F / Qs, jnp.where(const_mass, G, jnp.inf)
    )
    status = _status(raw, r, drifted, ok_end, h1)
    g = Event(kind, sigma, (target - q0) / Qs).value(x_e, v_e, a_e)
    ends = (status.astype(jnp.int32), q_end, qdot_end, a_e, g, jerk)
    return ends, terms


# The central difference's step along the flow (lane units).
_CENTRAL = 1e-5


def _central_points(s_e, x_e, v_e, a_e):
    """Where the central difference of `_central_jerk` reads the acceleration."""
    d = _CENTRAL
    return [
        (s_e + d, x_e + v_e * d + 0.5 * a_e * d**2, v_e + a_e * d),
        (s_e - d, x_e - v_e * d + 0.5 * a_e * d**2, v_e - a_e * d),
    ]


def _central_jerk(ahead, behind):
    """The jerk by a central difference along the flow: where the user's L has a
    removable singularity in a third derivative exactly at the event (x ** p with an
    array of exponents at x = 0 gives 0 * inf). `ahead`, `behind`: the
    accelerations at `_central_points`."""
    return (ahead - behind) / (2 * _CENTRAL)


def _event_time(r, kind, sigma, raw, s_e, v_e, a_e, g, jerk, q_end, qdot_end):
    """The event time and end state with the event's tangent. The loop's step lengths
    carry no tangent (the controller's choices are not differentiated); the event
    time's is the implicit function's, ds = -dg/ġ at g = 0, added with a zero
    primal."""
    Qs, tau = r.Qs, r.tau
    event = Event(kind, sigma, None)
    gdot = jnp.where(kind == MAX_SPEED, sigma * jerk, event.slope(v_e, a_e))
    # The tangent of ġ multiplies g, zero to rounding, and is dropped: differentiating
    # the jerk (a third derivative of L) again triples the compile time of a gradient.
    gdot = jax.lax.stop_gradient(gdot)
    corr = -g / jnp.where(gdot != 0, gdot, 1.0)
    # A correction that is not finite carries no tangent and must not touch the
    # value (its primal contribution is zero).
    corr = jnp.where(jnp.isfinite(corr), corr, 0.0)
    # Only a located event defines its time by g = 0: any other end state (one that
    # "matched" may use as its meeting point) is the state at a time, whose tangent
    # is the state's own.
    corr = jnp.where(raw == LOCATED, corr, 0.0)
    dcorr = corr - jax.lax.stop_gradient(corr)  # zero, with the event's tangent
    t_e = tau * (s_e + dcorr)
    # The state at the event moves with it: (x, v) + (v, a) δs to first order. The
    # event's position is the target of "matched"'s second leg: without this its
    # derivative with respect to a parameter of L is wrong.
    q_end = q_end + Qs * v_e * dcorr
    qdot_end = qdot_end + (Qs / tau) * a_e * dcorr
    return t_e, q_end, qdot_end


def finish(L, consts, q0, targets, kinds, rtols, out, rel, energy_tol, legs=None):
    """Statuses, event times and end states (`Ends`) and the error bound's sums in
    time units (`BoundTerms`) from the loop's output `out` (vmapped over lanes).
    `rel`: each lane's `Release`; `legs`: `leg_ends`' outputs, where the caller
    has them (`CompactMechanics.release_and_leg_ends`)."""
    mech = mechanics(L, consts)
    sums = (
        out.sums
        if out.sums is not None
        else tuple(jnp.zeros_like(q0) for _ in range(4))
    )
    s_e, x_e, v_e = out.s, out.x, out.v
    per_lane = (targets, kinds, rtols, out.sigma, out.raw, s_e, x_e, v_e)
    # (The compact tier's quantities from one evaluation site: the central
    # difference's accelerations `accels` with the ends'.)
    if legs is None:
        legs = mech.leg_ends(rel, s_e, x_e, v_e, _central_points)
    legs, accels = legs
    one = lambda *a: _lane_end(energy_tol, *a)
    ends, terms = jax.vmap(one)(rel, legs, *per_lane, *sums)
    # One fusion for the per-lane outputs, so that L's values at the two ends of the
    # leg (energies, mass, acceleration, jerk) are computed once each, not once per
    # reader (each a libm sine or cosine per lane for the pendulum).
    ends, terms = fused(ends, terms)
    status, q_end, qdot_end, a_e, g, jerk = ends
    # (The central difference only where some jerk is not finite: two more
    # accelerations per lane otherwise.)
    bad = ~jnp.isfinite(jerk)
    if accels is not None:
        jerk = jnp.where(bad, _central_jerk(*accels), jerk)
    else:
        central = lambda r, *p: _central_jerk(*mech.end_accels(r, _central_points(*p)))
        jerk = jax.lax.cond(
            jnp.any(bad),
            lambda: jnp.where(bad, jax.vmap(central)(rel, s_e, x_e, v_e, a_e), jerk),
            lambda: jerk,
        )
    lanes = (rel, kinds, out.sigma, out.raw, s_e, v_e, a_e, g, jerk)
    t_e, q_end, qdot_end = jax.vmap(_event_time)(*lanes, q_end, qdot_end)
    return Ends(status, t_e, q_end, qdot_end), terms


# A failed lane whose mass ∂²L/∂q̇² falls below this fraction of its largest value
# between the release point and the far side of the swing failed because of the
# coordinates (Huygens' cycloid in θ near its cusp: the mass is 2mR²(1 - cos θ)).
_VANISHING_MASS = 1e-6
_MASS_SAMPLES = 33


@eqx.filter_jit
def blame_coordinates(L, consts, q0, q_far, status):
    """`coordinate_singularity` for failed lanes whose mass vanishes on the swing."""
    dtype = q0.dtype
    z1, z = jnp.zeros((1,), dtype), jnp.zeros((), dtype)
    mech = mechanics(L, consts)

    def mass(q):
        _, (M, _) = mech.accelerations(jnp.reshape(q, (1,)), z1, z, fuse=False)
        return jnp.abs(M[0, 0])

    def vanishes(q0, q_far):
        w = jnp.linspace(0.0, 1.0, _MASS_SAMPLES, dtype=dtype)
        ms = jax.vmap(mass)(q0 + w * (q_far - q0))
        ms = jnp.where(jnp.isfinite(ms), ms, 0.0)
        return jnp.min(ms) <= _VANISHING_MASS * jnp.max(ms)

    # A mass singular at the release point already has its own status.
    failed = (
        (status != SUCCESS) & (status != SINGULAR_MASS) & (status != NONFINITE_INPUT)
    )
    failed = failed & jnp.isfinite(q0) & jnp.isfinite(q_far)
    # Only failed lanes need it: under vmap the check costs 33 mass evaluations for
    # every lane, so it is skipped (lax.cond) when no lane failed.
    blame = jax.lax.cond(
        jnp.any(failed),
        lambda: jax.vmap(vanishes)(q0, jnp.where(failed, q_far, q0)) & failed,
        lambda: jnp.zeros_like(failed),
    )
    return jnp.where(blame, COORDINATE_SINGULARITY, status)
