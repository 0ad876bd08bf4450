r"""What became of a period: one status enumeration, `PeriodStatus`, for `period`,
`sweep_periods` and `quadrature_period`, and its int codes."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import is_concrete


class PeriodStatus(eqx.Enumeration):
    r"""The statuses of a period (`period`, `sweep_periods`, `quadrature_period`):
    an `equinox.Enumeration`, as `diffrax.RESULTS` is for a diffrax solve, but its
    own members. Each member's value is its message, and
    `PeriodStatus.<member>.error_if(x, pred)` raises that message under `jit` as well
    as eagerly. Arrays of statuses (`SweepResult.status`, `QuadratureResult.status`,
    the CLI's CSV/NPZ) hold the int codes below: `status_code(member)` gives a
    member's code, `status_member(code)` a code's member, `status_message(code)` its
    message, and `STATUS_CODES` maps each code to its member's name. The codes are
    fixed; new members only ever go at the end.

    | code | member | meaning |
    | --- | --- | --- |
    | 0 | `success` | the period is trustworthy to about the tolerances |
    | 1 | `not_oscillating` | released at an equilibrium, the coordinate ran away, or no turning point before `t_max` |
    | 2 | `max_steps` | `max_steps` reached before the next turning point |
    | 3 | `singular_mass` | mass matrix singular or indefinite at release or on the path |
    | 4 | `root_find_failed` | the turning point could not be located |
    | 5 | `energy_drift` | energy not conserved to `energy_tol`: the trajectory is garbage |
    | 6 | `solver_failed` | other ODE solver failure (collapsed step size, non-finite state, a Taylor step across a switch of the acceleration) |
    | 7 | `nonfinite_input` | `q0` is NaN or infinite |
    | 8 | `unresolved` | (quadrature) too close to an unstable equilibrium for this precision |
    | 9 | `not_natural` | (quadrature) `L` is not $\frac12 m(q)\dot q^2 - V(q)$ |
    | 10 | `escapes` | (quadrature) no turning point ahead: the motion is unbounded |
    | 11 | `nonfinite_period` | (quadrature) the period came out non-finite |
    | 12 | `tolerance_not_met` | the per-lane error estimate exceeds what `rtol` promises |
    | 13 | `coordinate_singularity` | the path runs into a coordinate singularity |
    | 14 | `not_symmetric` | `method="quarter"` on a well that is not mirror-symmetric |

    `quadrature_period` reports a release at an equilibrium as 1, like the
    integrators; a motion with no turning point ahead gets its own code 10 there,
    because quadrature can tell it apart from other ways of not oscillating (the
    integrators report a runaway as 1).
    """  # noqa: E501

    success = "success"
    not_oscillating = (
        "does not oscillate: released at rest at an equilibrium (zero acceleration, "
        "V'(q0) = 0 to within the rounding of q0), or the coordinate ran away (no "
        "turning point ahead; in a solve |q - q0| > 1e6 max(|q0|, 1), which is also "
        "what a path through a coordinate singularity can look like), or no turning "
        "point before t_max"
    )
    max_steps = (
        "max_steps reached before the next turning point: raise max_steps or loosen "
        "the tolerances; thousands of steps for one swing usually mean a coordinate "
        "singularity on the path (e.g. the cycloid's cusp in θ; reparametrize)"
    )
    singular_mass = (
        "singular or indefinite mass matrix ∂²L/∂q̇² (at the release point, on the "
        "path or where the solve stopped): a coordinate singularity; change "
        "coordinates with lagrax.reparametrize"
    )
    root_find_failed = (
        "turning point not located: the refinement to q̇ = 0 did not converge (zero "
        "or non-finite acceleration at the turning point), or by quadrature the energy "
        "balance has no reliable root (or a barrier lies inside the swing)"
    )
    energy_drift = (
        "energy drift beyond energy_tol between release and turning point: the "
        "trajectory is not trustworthy (tighten the tolerances, or a coordinate "
        "singularity was crossed)"
    )
    solver_failed = (
        "the ODE solver failed (step size collapsed or non-finite state) away from "
        "any detectable singularity of the mass matrix (in a sweep: or a sine or "
        "cosine in the equations took an argument beyond 8.2e5, which the kernel's "
        "vectorized sine does not cover; or, with lagrax.Taylor, the acceleration is "
        "not smooth on the path: a branch of jnp.where, abs, max, ... switched inside "
        "a step, whose polynomial continues the old branch: step with a Runge-Kutta "
        "solver such as diffrax.Dopri8())"
    )
    nonfinite_input = "the release point q0 is not finite"
    unresolved = (
        "unresolved: too close to an unstable equilibrium for this precision (the far "
        "turning point cannot be resolved; the period there is dominated by rounding)"
    )
    not_natural = (
        "L is not natural: not of the form m(q) qdot^2 / 2 - V(q) (a term linear or "
        "beyond quadratic in qdot, or explicit time dependence), which "
        "quadrature_period needs"
    )
    escapes = (
        "does not oscillate: no turning point ahead (the energy is above every "
        "barrier in the direction of motion; the motion is unbounded)"
    )
    nonfinite_period = "the period came out non-finite"
    tolerance_not_met = (
        "the per-lane error estimate exceeds what rtol promises: the period is not "
        "reported (near a separatrix, float64 rounding of the energy limits any method "
        "that integrates through the bottom of the swing; for a mirror-symmetric well "
        "use method='quarter', or loosen rtol)"
    )
    coordinate_singularity = (
        "the path runs into a coordinate singularity (the mass ∂²L/∂q̇² vanishes on "
        "it, e.g. Huygens' cycloid written in θ released near its cusp): change "
        "coordinates with lagrax.reparametrize (for the cycloid, the u = cos(θ/2) form "
        "in lagrax.systems.cycloid)"
    )
    not_symmetric = (
        "not mirror-symmetric: method='quarter' computes T = 4 t(q0 -> q_m) for a "
        "well symmetric about its point of maximum speed q_m, but the mirror image of "
        "q0 is not a turning point here; use the default method='matched'"
    )


#: The int view of `PeriodStatus`: `{code: member name}`, e.g. `STATUS_CODES[3]` is
#: `"singular_mass"`. Fixed: new members only ever go at the end.
STATUS_CODES = {
    0: "success",
    1: "not_oscillating",
    2: "max_steps",
    3: "singular_mass",
    4: "root_find_failed",
    5: "energy_drift",
    6: "solver_failed",
    7: "nonfinite_input",
    8: "unresolved",
    9: "not_natural",
    10: "escapes",
    11: "nonfinite_period",
    12: "tolerance_not_met",
    13: "coordinate_singularity",
    14: "not_symmetric",
}
_MEMBERS = [getattr(PeriodStatus, name) for name in STATUS_CODES.values()]
assert len(_MEMBERS) == len(PeriodStatus), "every member of PeriodStatus needs its code"

_CODE = {name: code for code, name in STATUS_CODES.items()}
SUCCESS = _CODE["success"]
NOT_OSCILLATING = _CODE["not_oscillating"]
MAX_STEPS = _CODE["max_steps"]
SINGULAR_MASS = _CODE["singular_mass"]
ROOT_FIND_FAILED = _CODE["root_find_failed"]
ENERGY_DRIFT = _CODE["energy_drift"]
SOLVER_FAILED = _CODE["solver_failed"]
NONFINITE_INPUT = _CODE["nonfinite_input"]
UNRESOLVED = _CODE["unresolved"]
NOT_NATURAL = _CODE["not_natural"]
ESCAPES = _CODE["escapes"]
NONFINITE_PERIOD = _CODE["nonfinite_period"]
TOLERANCE_NOT_MET = _CODE["tolerance_not_met"]
COORDINATE_SINGULARITY = _CODE["coordinate_singularity"]
NOT_SYMMETRIC = _CODE["not_symmetric"]


def status_code(result: PeriodStatus):
    """The int view of a `PeriodStatus` member (an int32 array under `jit`/`vmap`)."""
    # By the enumeration's public comparisons: its members' own int values are
    # equinox's business.
    return jnp.select(
        [result == member for member in _MEMBERS],
        [np.int32(code) for code in STATUS_CODES],
        np.int32(-1),
    )


def status_member(code) -> PeriodStatus:
    """The `PeriodStatus` member of an int status code (or an array of them, under `jit`
    too, where an unknown code reads as `success`).

    **Raises:** `ValueError` for a concrete code that is not one of `STATUS_CODES`.
    """
    code = jnp.asarray(code, jnp.int32)
    if is_concrete(code) and not np.isin(np.asarray(code), list(STATUS_CODES)).all():
        raise ValueError(
            f"`code` must be one of the integer status codes {sorted(STATUS_CODES)}; "
            f"got {np.asarray(code)!r}."
        )

    def member(c):
        out = _MEMBERS[0]
        for k, item in enumerate(_MEMBERS[1:], 1):
            out = PeriodStatus.where(c == k, item, out)
        return out

    for _ in range(code.ndim):  # (`PeriodStatus.where` takes a scalar predicate)
        member = jax.vmap(member)
    return member(code)


def status_message(code) -> str:
    r"""The meaning of a status code of `period`, `sweep_periods` or
    `quadrature_period`, as one line of text.

    The codes are the int view of `lagrax.PeriodStatus` (its docstring has the
    table; `lagrax.STATUS_CODES` maps codes to names).

    **Arguments:** `code`: an int (or integer scalar array).

    **Returns:** the message, e.g. `"success"`.

    **Raises:** `ValueError` for anything but one of the codes.
    """
    try:
        key = int(code)
        known = key == code and key in STATUS_CODES
    except (TypeError, ValueError):
        known = False
    if not known:
        raise ValueError(
            f"`code` must be one of the integer status codes {sorted(STATUS_CODES)}; "
            f"got {code!r}."
        )
    return PeriodStatus[status_member(np.int32(key))]


def first_of(*pairs, default):
    """A status from `(condition, code)` pairs: the first true condition wins
    (`jnp.select`, written as pairs so that each cause sits next to its code)."""
    conditions, codes = zip(*pairs)
    return jnp.select(list(conditions), list(codes), default)


def error_if(x, status):
    """`x`, raising (under `jit` too) with the message of the first failed `status`.

    `status`: int codes of any shape; raises when any is not `success`.
    """
    flat = jnp.ravel(jnp.asarray(status))
    first = flat[jnp.argmax(flat != SUCCESS)]
    return status_member(first).error_if(x, jnp.any(flat != SUCCESS))
