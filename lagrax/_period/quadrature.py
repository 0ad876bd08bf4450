r"""The period of a one-degree-of-freedom natural system by quadrature.

For $L = \frac12 m(q)\dot q^2 - V(q)$ released from rest at $q_0$ (energy $E = V(q_0)$),

$$T = 2\int_a^b \sqrt{\frac{m(q)}{2\,(E - V(q))}}\,dq,$$

between the turning points $a < b$ ($q_0$ one of them). This is an oracle independent of
any ODE solver, for systems without a closed-form period. Numerically the integrand
has inverse-square-root singularities at both ends, and $E - V(q)$ near a turning point
is a difference of nearly equal numbers (for the pendulum near the bottom,
$\cos q - \cos q_0$ is all rounding error). Both are removed here:

- $q = c + h\sin\varphi$ with $c = (a+b)/2$, $h = (b-a)/2$, and near each end
  $E - V(q) = |q - q_e|\,\bar A$ where $\bar A$ is the mean of $\mp V'$ between $q$ and
  that end $q_e$. Then $h\cos\varphi/\sqrt{E - V} = \sqrt{h(1 \pm \sin\varphi)/\bar A}$:
  smooth, no cancellation, Gauss–Legendre converges exponentially.
- $\bar A$ is itself a (short) Gauss–Legendre quadrature of $V'$, a sum of terms of one
  sign: relative accuracy without ever subtracting two values of $V$.
- The far turning point solves $\int_{q_0}^{q_1} V'(q)\,dq = 0$: bracketed on a
  geometric grid, narrowed by bisection, polished by Newton steps.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._checks import (
    as_real_array,
    check_finite,
    check_one_dof,
    is_concrete,
    positive_int,
    positive_scalar,
)
from .._custom_types import Lagrangian
from .._results import (
    error_if,
    ESCAPES,
    first_of,
    NONFINITE_PERIOD,
    NOT_NATURAL,
    NOT_OSCILLATING,
    ROOT_FIND_FAILED,
    SINGULAR_MASS,
    STATUS_CODES,
    status_message,
    SUCCESS,
    UNRESOLVED,
)


# The statuses are `lagrax.PeriodStatus` (int view); these names are the quadrature's
# reasons, as codes of that one enumeration.
EQUILIBRIUM = NOT_OSCILLATING
ROOT_FAILED = ROOT_FIND_FAILED
NONFINITE = NONFINITE_PERIOD


class QuadratureResult(eqx.Module):
    r"""What `lagrax.quadrature_period` returns.

    - `periods`: the periods $T$, shaped like `q0`; NaN where `status != 0`.
    - `status`: int codes shaped like `q0`, the int view of `lagrax.PeriodStatus`
        (shared with `sweep_periods`; `lagrax.STATUS_CODES`): `success`,
        `not_oscillating` (at an equilibrium), `escapes`, `unresolved`,
        `singular_mass`, `root_find_failed`, `not_natural`, `nonfinite_period`. See
        `messages()` and `lagrax.status_message`.
    - `turning_points`: the far turning point $q_1$ reached from `q0` (NaN on failure).
    - `errors`: an estimate of the relative error of each period from rounding: the
        energy balance that locates $q_1$ is known only to about
        $\varepsilon\,|q_1 - q_0|\,\overline{|V'|}$, which matters near an unstable
        equilibrium (a hilltop), where the period depends on the log of the energy gap.
        Quadrature truncation is not included (it is below 1e-13 with the default
        nodes except near a hilltop). Points whose estimate exceeds `rtol` get
        status `unresolved`.
    """

    periods: Float[Array, "..."]
    status: Int[Array, "..."]
    turning_points: Float[Array, "..."]
    errors: Float[Array, "..."]

    def messages(self) -> list[str]:
        """One message per release point (flattened), for concrete results."""
        return [status_message(c) for c in np.ravel(self.status)]


# The bracket search: a grid of 352 distances, 2^(-24) to 2^64 times the local scale,
# and at most this many barrier tops passed below their top before giving up.
_GRID = 352
_GRID_BELOW = 96
_MAX_BARRIERS = 8


def _gauss_legendre(n: int):
    x, w = np.polynomial.legendre.leggauss(n)
    return x, w


def _natural_parts(L, dtype):
    t0 = jnp.zeros((), dtype)
    zero = jnp.zeros((), dtype)
    one = jnp.ones((), dtype)

    def Lq(q, v, t=t0):
        return L(jnp.reshape(q, (1,)), jnp.reshape(v, (1,)), t)

    def dV(q):
        return -jax.grad(Lq, argnums=0)(q, zero)

    def mass(q):
        p = lambda v: jax.grad(Lq, argnums=1)(q, v)
        return jax.jvp(p, (zero,), (one,))[1]

    def d2V(q):
        return jax.jvp(dV, (q,), (one,))[1]

    def natural(q):
        # L = L0 + c1 v + c2 v^2 + c3 v^3 + c4 v^4 + ...: these four residuals vanish
        # only when c1 = c3 = c4 = 0 (and there is no time dependence at v = 1).
        eps = jnp.finfo(dtype).eps
        L0, Lp, Lm = Lq(q, zero), Lq(q, one), Lq(q, -one)
        m = mass(q)
        p0 = jax.grad(Lq, argnums=1)(q, zero)
        # Any t far from 0 and from simple fractions will do; this is the fixed point
        # of cos (so no user's parameter is likely to make L(t) = L(0) by chance).
        Lt = Lq(q, one, jnp.asarray(0.7390851332151607, dtype))
        scale = jnp.abs(L0) + jnp.abs(Lp) + jnp.abs(Lm) + jnp.abs(m)
        tol = 1024 * eps * scale
        residuals = jnp.stack([Lp - L0 - m / 2, Lm - L0 - m / 2, p0, Lt - Lp])
        return jnp.all(jnp.abs(residuals) <= tol)

    return dV, d2V, mass, natural


def _rule01(n: int, dtype):
    """The Gauss–Legendre rule of `n` nodes on [0, 1]: nodes in (0, 1), weights
    summing to 1."""
    xs, ws = _gauss_legendre(n)
    return jnp.asarray((xs + 1) / 2, dtype), jnp.asarray(ws / 2, dtype)


def _folded_rule(nodes: int, dtype):
    """The outer rule in phi on [-pi/2, pi/2], folded onto the half nearer each end:
    theta = pi/2 - |phi| is the angular distance from that end, sigma = 1 - cos(theta)
    = 2 sin^2(theta/2) (distance from the end, in units of h), gamma = 1 + cos(theta)
    (the other factor of cos^2 phi = sigma * gamma). Returns `(sigma, gamma, w)`."""
    xs, ws = _gauss_legendre(nodes)
    half = xs > 0
    theta = (np.pi / 2) * (1 - xs[half])
    sigma = jnp.asarray(2 * np.sin(theta / 2) ** 2, dtype)
    gamma = jnp.asarray(2 * np.cos(theta / 2) ** 2, dtype)
    return sigma, gamma, jnp.asarray((np.pi / 2) * ws[half], dtype)


def _bracket(dV_c, q0_c, f0_c, k0_c, s, scan):
    """A bracket `[lower, upper]` of distances to the far turning point, whether it
    was `found`, and whether the motion `escapes` (no turning point ahead).

    Along the direction of motion, on a quarter-octave grid of distances around the
    local scale |V'/V''|, the energy gain G(ell) = V(q0 + s ell) - V(q0) (cumulative
    integrals of V', accurate at every scale) and the force. The turning point is the
    first zero of G; near a hilltop G is >= 0 only in a window narrower than a grid
    step, so each barrier top met on the way (force turning from uphill to downhill)
    is located and G tested there too; a barrier passed below its top lets the
    search go on."""
    dtype = q0_c.dtype
    tiny = jnp.finfo(dtype).tiny
    scan_tau, scan_w = scan
    scale = jnp.minimum(
        jnp.abs(f0_c) / jnp.maximum(jnp.abs(k0_c), tiny),
        jnp.maximum(jnp.abs(q0_c), 1.0),
    )
    scale = jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0)
    grid = scale * jnp.exp2((jnp.arange(_GRID, dtype=dtype) - _GRID_BELOW) / 4)
    edges = jnp.concatenate([jnp.zeros((1,), dtype), grid])

    def integral(l0, l1):
        # The integral of s V'(q0 + s x) over x in [l0, l1].
        xs = l0 + (l1 - l0) * scan_tau
        return (l1 - l0) * jnp.sum(scan_w * s * jax.vmap(dV_c)(q0_c + s * xs))

    G = jnp.cumsum(jax.vmap(integral)(edges[:-1], edges[1:]))
    F = s * jax.vmap(dV_c)(q0_c + s * grid)
    F_prev = jnp.concatenate([-jnp.abs(f0_c)[None], F[:-1]])
    top = (F_prev > 0) & (F <= 0)
    event = (G >= 0) | top
    index = jnp.arange(_GRID)

    def search(state):
        start, _, _, _, count = state
        later = event & (index >= start)
        j = jnp.argmax(later)
        l_prev, l_j = edges[j], edges[j + 1]

        def bisect_top(_, bracket):
            lo, hi = bracket
            mid = lo + (hi - lo) / 2
            uphill = s * dV_c(q0_c + s * mid) > 0
            return jnp.where(uphill, mid, lo), jnp.where(uphill, hi, mid)

        _, l_top = jax.lax.fori_loop(0, 64, bisect_top, (l_prev, l_j))
        G_top = jnp.where(j > 0, G[jnp.maximum(j - 1, 0)], 0.0) + integral(
            l_prev, l_top
        )
        hit = jnp.where(top[j], G_top >= 0, True)
        flag = jnp.where(jnp.any(later), jnp.where(hit, 1, 0), 2)
        hi = jnp.where(top[j], l_top, l_j)
        return j + 1, l_prev, hi, flag, count + 1

    _, lower, upper, flag, _ = jax.lax.while_loop(
        lambda state: (state[3] == 0) & (state[4] < _MAX_BARRIERS),
        search,
        (jnp.zeros((), int), jnp.zeros((), dtype), jnp.ones((), dtype), 0, 0),
    )
    return lower, upper, flag == 1, flag == 2


def _bisect(mean_force_c, lower, upper, found, root):
    """32 halvings of the bracket on the mean force over [0, ell] (to ~1e-11
    relative), without gradients. Hand-written rather than optimistix.Bisection: a
    fixed count is all vmap needs, and it compiles faster. Returns `(ell, safe,
    upper_safe)`."""
    safe = found & jnp.isfinite(upper)
    upper_safe = jnp.where(safe, upper, 1.0)
    lower_safe = jnp.where(safe, lower, 0.5)

    def halve(_, bracket):
        lo, hi = bracket
        mid = lo + (hi - lo) / 2
        below = mean_force_c(mid, *root)[0] < 0
        return jnp.where(below, mid, lo), jnp.where(below, hi, mid)

    lo, hi = jax.lax.fori_loop(0, 32, halve, (lower_safe, upper_safe))
    return lo + (hi - lo) / 2, safe, upper_safe


def _newton(mean_force, dV, q0, s, ell, lower, upper_safe, root):
    """Newton on G(ell) = V(q0 + s ell) - V(q0) = ell * mean force, G' = s V'(q1):
    quadratic convergence to rounding in two or three steps, and the implicit
    derivative of the far turning point."""

    def step(ell, _):
        g, _ = mean_force(ell, *root)
        slope = s * dV(q0 + s * ell)
        new = ell - ell * g / jnp.where(slope != 0, slope, 1.0)
        # Stay in the bracket (a where, not a clip: the root may sit on a grid point,
        # and a clip there would zero the derivative). A 1% margin: the root may also
        # sit exactly on the bracket's end.
        inside = jnp.isfinite(new) & (new >= 0.99 * lower) & (new <= 1.01 * upper_safe)
        return jnp.where(inside, new, ell), None

    return jax.lax.scan(step, ell, None, length=3)[0]


def _folded_half_period(dV, mass, a, b, h, folded, inner):
    """The folded quadrature: T/2 and whether the mean slopes and masses on the way
    were positive. Near the end q_e the distance is h*sigma and E - V(q) =
    h*sigma*A, A = mean of (+V' towards b, -V' towards a) on it."""
    sigma, gamma, outer_w = folded
    inner_tau, inner_w = inner

    def side(end, sign):
        dist = h * sigma
        qs = end - sign * dist

        def mean_slope(d):
            return sign * jnp.sum(inner_w * jax.vmap(dV)(end - sign * d * inner_tau))

        A = jax.vmap(mean_slope)(dist)
        ms = jax.vmap(mass)(qs)
        terms = jnp.sqrt(h * gamma * ms / (2 * A))
        return jnp.sum(outer_w * terms), jnp.all(A > 0), jnp.all(ms > 0)

    Ta, A_ok_a, m_ok_a = side(a, -1.0)
    Tb, A_ok_b, m_ok_b = side(b, 1.0)
    return Ta + Tb, A_ok_a & A_ok_b, m_ok_a & m_ok_b


def _period_one(L, q0, rtol, nodes: int, inner_nodes: int):
    dtype = q0.dtype
    eps = jnp.finfo(dtype).eps
    tiny = jnp.finfo(dtype).tiny
    dV, d2V, mass, natural = _natural_parts(L, dtype)
    nan = jnp.asarray(jnp.nan, dtype)
    scan, root, inner = (_rule01(k, dtype) for k in (16, nodes, inner_nodes))
    folded = _folded_rule(nodes, dtype)

    f0 = dV(q0)
    k0 = d2V(q0)
    m0 = mass(q0)
    s = jnp.where(f0 > 0, -1.0, 1.0).astype(dtype)  # direction of motion from rest

    def mean_force(ell, tau, w, q0=q0):
        # The mean over [q0, q0 + s ell] of s V', and the mean of |V'| (rounding scale).
        forces = s * jax.vmap(dV)(q0 + s * ell * tau)
        return jnp.sum(w * forces), jnp.sum(w * jnp.abs(forces))

    # The bracket and the bisection locate q1 to ~1e-11 without gradients (loops of
    # data-dependent length are not reverse-differentiable); the Newton steps then
    # give the implicit derivative of q1, so the period is differentiable in q0 and
    # in parameters of L.
    q0_c, f0_c, k0_c = jax.lax.stop_gradient((q0, f0, k0))
    dV_c = lambda q: jax.lax.stop_gradient(dV(q))
    mean_force_c = lambda *a: jax.lax.stop_gradient(mean_force(*a, q0_c))
    lower, upper, found, escapes = _bracket(dV_c, q0_c, f0_c, k0_c, s, scan)
    ell, bisection_ok, upper_safe = _bisect(mean_force_c, lower, upper, found, root)
    ell = _newton(mean_force, dV, q0, s, ell, lower, upper_safe, root)
    g_end, g_abs = mean_force(ell, *root)
    q1 = q0 + s * ell
    f1 = dV(q1)
    k1 = d2V(q1)
    a = jnp.minimum(q0, q1)
    b = jnp.maximum(q0, q1)
    half_T, A_ok, m_ok = _folded_half_period(dV, mass, a, b, ell / 2, folded, inner)
    T = 2 * half_T

    # Statuses, in order of precedence (the first that applies wins).
    natural_ok = natural(q0) & jnp.where(found, natural(q1), True)
    at_equilibrium = (f0 == 0) | (jnp.abs(f0) <= 4 * eps * jnp.abs(q0) * jnp.abs(k0))
    # The energy balance that defines q1 is known to about eps_G = eps * ell * mean|V'|
    # (rounding of V' and of the nodes, intrinsic to evaluating V' in this precision;
    # the q0 side is exact). That shifts the energy gap g = V'(q1)^2 / (2 |V''(q1)|)
    # of the q1 side by eps_G; near a hilltop T ~ sqrt(m/k) ln(1/g), so
    # dT/T ~ 2 eps_G sqrt(m k) / (V'(q1)^2 T), which is also ~eps_G/E for a plain
    # well (on the pendulum near pi, 1-3x the actual error).
    m1 = mass(q1)
    eps_G = eps * ell * g_abs
    estimate = (
        2 * eps_G * jnp.sqrt(jnp.abs(m1 * k1)) / jnp.maximum(f1**2 * jnp.abs(T), tiny)
    )
    estimate = jnp.maximum(estimate, 4 * eps)
    unresolved = ~(estimate <= rtol)
    # Beyond linearisation: q1 uncertain by more than 1e-4 of its own turning region.
    lost = ~(eps_G * jnp.abs(k1) <= 1e-4 * f1**2)
    root_ok = (
        bisection_ok & jnp.isfinite(ell) & (jnp.abs(g_end) <= 1e3 * eps * g_abs + tiny)
    )
    status = first_of(
        (~natural_ok, NOT_NATURAL),
        (~(m0 > 0), SINGULAR_MASS),
        (at_equilibrium, EQUILIBRIUM),
        (escapes, ESCAPES),
        (found & lost, UNRESOLVED),
        (~found, ROOT_FAILED),
        (~root_ok | ~A_ok, ROOT_FAILED),
        (~(m_ok & (m1 > 0)), SINGULAR_MASS),
        (unresolved, UNRESOLVED),
        (~jnp.isfinite(T), NONFINITE),
        default=SUCCESS,
    )
    ok = status == SUCCESS
    return (
        jnp.where(ok, T, nan),
        status,
        jnp.where(ok, q1, nan),
        jnp.where(ok, estimate, nan),
    )


@eqx.filter_jit
def _periods(L, flat, rtol, nodes, inner_nodes):
    # One compiled program per (L, shape, nodes): L is a static argument (hashed by
    # identity), so repeated calls with the same Lagrangian do not recompile.
    return jax.vmap(lambda x: _period_one(L, x, rtol, nodes, inner_nodes))(flat)


def quadrature_period(
    L: Lagrangian,
    q0,
    *,
    rtol=1e-12,
    nodes: int = 128,
    inner_nodes: int = 32,
    throw: bool = True,
) -> QuadratureResult:
    r"""The period of a 1-DOF natural system released from rest, by quadrature.

    For $L = \frac12 m(q)\dot q^2 - V(q)$ released from rest at $q_0$,

    $$T = 2\int_a^b \sqrt{\frac{m(q)}{2\,(V(q_0) - V(q))}}\,dq,$$

    with $a < b$ the two turning points ($q_0$ and the far one $q_1$, found as the first
    zero of $\int_{q_0}^{q_1} V' = 0$ in the direction of motion). $m(q) = \partial^2
    L/\partial\dot q^2$ and $V'(q) = -\partial L/\partial q$ are taken from `L` itself
    at $\dot q = 0$, $t = 0$. The endpoint singularities are removed by $q = c + h
    \sin\varphi$ and every energy difference is computed as an integral of $V'$ (never a
    difference of two values of $V$), so the result is accurate to ~1e-13 at small
    amplitudes as well as large; this is an oracle independent of any ODE solver, and a
    fast path (about `nodes * inner_nodes` evaluations of $V'$, no time stepping).

    Asymmetric potentials are fine: $q_1$ is the actual turning point, not a mirror
    image. Works under `jit` and `vmap` (over `q0`, and over parameters closed over by
    `L`), and is differentiable in `q0` and such parameters.

    **Arguments:**

    - `L`: the Lagrangian `L(q, qdot, t) -> scalar` of one degree of freedom (`q` of
        shape `(1,)`); it must be natural: quadratic in $\dot q$ with no linear term and
        no explicit time dependence (checked at $q_0$ and $q_1$, per release point).
    - `q0`: the release points, an array of any shape (each entry one release from
        rest); a scalar gives a scalar period.
    - `rtol`: the largest acceptable estimated relative error (`errors`); a release
        point beyond it (too near a hilltop for this precision) gets status
        `unresolved` and no number. An array: changing it does not recompile. A
        threshold on the result, not a step tolerance: its default, 1e-12, sits
        above what the default rule reaches, where the integrators' 1e-13 steers
        their steps.
    - `nodes`: Gauss–Legendre nodes of the outer rule (even; static). 128 reaches
        ~1e-13 for the pendulum up to ~1e-2 from the top; releases nearer an unstable
        equilibrium need more (or get status `unresolved`).
    - `inner_nodes`: nodes of the inner rule that averages $V'$ (static).
    - `throw`: raise if any release point fails. With `throw=False` failures are in
        `status` and their periods are NaN.

    **Returns:**

    A `QuadratureResult` with `periods`, `status` (0 = success; the codes are listed
    there and `lagrax.status_message` spells them out) and `turning_points`.
    Releases that do not oscillate are reported as such, never as a number: at an
    equilibrium (the pendulum at the bottom, or at $\pi$ to within the rounding of
    $q_0$), with no turning point ahead, or too near a hilltop for the turning point to
    be resolved (status `unresolved`). (Beyond the top, e.g. the pendulum released at
    rest at $\pi + 0.1$, the motion is a swing about $2\pi$, and that period is
    returned.)

    **Raises:**

    - `TypeError`: `L` not callable, `q0` not a real float array.
    - `ValueError`: `q0` empty or not finite (eager), `nodes`/`inner_nodes` not a
        positive even/positive int; and with `throw=True`, in an eager call, any release
        point that fails (the message names it and why).

    **Example:**

    ```python
    L = lagrax.systems.pendulum.lagrangian()
    res = lagrax.quadrature_period(L, jnp.linspace(0.1, 3.0, 30))
    res.periods  # lagrax.systems.pendulum.period(jnp.linspace(0.1, 3.0, 30)), to ~1e-14
    ```
    """
    for name, value in (("nodes", nodes), ("inner_nodes", inner_nodes)):
        positive_int(value, name, minimum=2)
    if nodes % 2:
        raise ValueError(f"`nodes` must be even; got {nodes}.")
    q0 = as_real_array(q0, "q0")
    if q0.size == 0:
        raise ValueError(
            f"`q0` must hold at least one release point; got shape {q0.shape}."
        )
    eager = is_concrete(q0)
    rtol = positive_scalar(rtol, "rtol", q0.dtype)
    check_finite(q0, "q0")
    check_one_dof(L, q0.dtype)

    flat = jnp.ravel(q0)
    T, status, q1, est = _periods(L, flat, rtol, nodes, inner_nodes)
    result = QuadratureResult(
        periods=T.reshape(q0.shape),
        status=status.reshape(q0.shape),
        turning_points=q1.reshape(q0.shape),
        errors=est.reshape(q0.shape),
    )
    if throw:
        if eager and is_concrete(result.status):
            codes = np.ravel(np.asarray(result.status))
            where = np.flatnonzero(codes != SUCCESS)
            if where.size:
                first = where[0]
                raise ValueError(
                    f"lagrax.quadrature_period failed for {where.size} of {codes.size} "
                    f"release points; the first is q0={float(np.ravel(q0)[first])!r}: "
                    f"status {codes[first]} ({STATUS_CODES[codes[first]]}): "
                    f"{status_message(codes[first])}. Pass throw=False to get "
                    "per-point `status` and NaN periods instead."
                )
        else:  # the first failed point's own message, under jit too
            result = error_if(result, result.status)
    return result
