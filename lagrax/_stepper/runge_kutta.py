r"""An explicit Runge–Kutta step written out stage by stage from a diffrax tableau.

diffrax's `AbstractERK.step` loops over its stages with general tree operations: under
`vmap` on a CPU the loop around a cheap vector field costs several times the field.
Here each stage is plain elementwise code with the tableau's coefficients as
constants (read from diffrax's `ButcherTableau`, never copied by hand), and the step's
outputs leave through one fusion: each stage is read by several later ones, so XLA
would otherwise keep every stage a kernel of its own.
"""

import functools
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .base import (
    AbstractStepper,
    fused,
    LaneField,
    StepResult,
    within_or_identity,
)


def _combine(coeffs, ks):
    """sum_j coeffs[j] ks[j], skipping exact zeros (the tableaux are sparse)."""
    out = None
    for cj, kj in zip(coeffs, ks):
        if cj == 0.0:
            continue
        term = cj * kj
        out = term if out is None else out + term
    return out


def _rms(a, b):
    """The root mean square of two per-coordinate ratios, per lane."""
    if a.ndim <= 1:
        return jnp.sqrt(0.5 * (a**2 + b**2))
    axes = tuple(range(1, a.ndim))
    return jnp.sqrt(0.5 * jnp.mean(a**2 + b**2, axis=axes))


class RungeKuttaStepper(AbstractStepper):
    """The step of an explicit embedded Runge–Kutta pair (coefficients as Python
    floats: constants in the compiled step), with diffrax's error norm."""

    a: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    b: tuple[float, ...] = eqx.field(static=True)
    e: tuple[float, ...] = eqx.field(static=True)
    c: tuple[float, ...] = eqx.field(static=True)
    fsal: bool = eqx.field(static=True)
    error_order: float = eqx.field(static=True)
    rejects: ClassVar[bool] = True

    @staticmethod
    def of(solver) -> "RungeKuttaStepper | None":
        """The stepper of a diffrax explicit Runge–Kutta pair, or None for any other
        solver (implicit, or without an embedded error estimate)."""
        if not isinstance(solver, dfx.AbstractERK):
            return None
        # Read once per solver: converting diffrax's tableau to floats is slower
        # than a small sweep's dispatch, and every sweep asks twice (checks, kernel).
        try:
            return _stepper_of(solver)
        except TypeError:  # an unhashable solver (array fields): read it anew
            return _read_stepper(solver)

    def stages(self, accel, s, x, v, a, h):
        """The state at `s + h`, the acceleration there (FSAL) and the error estimate
        `(ex, ev)` of one step of the tableau."""
        kx, kv = [v], [a]
        for ci, row in zip(self.c[:-1] if self.fsal else self.c, self.a):
            dx, dv = _combine(row, kx), _combine(row, kv)
            xi = x if dx is None else x + h * dx
            vi = v if dv is None else v + h * dv
            kx.append(vi)
            kv.append(accel(s + ci * h, xi, vi))
        x1 = x + h * _combine(self.b, kx)
        v1 = v + h * _combine(self.b, kv)
        # The field at the new point: for a FSAL tableau it is the last stage (whose
        # weight in b_error is not zero for Tsit5, Dopri5, Bosh3), else one more call.
        a1 = accel(s + h, x1, v1)
        if self.fsal:
            kx.append(v1)
            kv.append(a1)
        ex, ev = h * _combine(self.e, kx), h * _combine(self.e, kv)
        return x1, v1, a1, ex, ev

    def step(
        self, field: LaneField, s, x, v, a, h, rtol, atol, *, free, cap, within=None
    ) -> StepResult:
        # Every lane takes `h` (the controller's choice): `free` and `cap` do not apply.
        del free, cap
        x1, v1, a1, ex, ev = self.stages(field.accel, s, x, v, a, h)
        sx = atol + rtol * jnp.maximum(jnp.abs(x), jnp.abs(x1))
        sv = atol + rtol * jnp.maximum(jnp.abs(v), jnp.abs(v1))
        err = _rms(ex / sx, ev / sv)
        raw = within_or_identity(within)(StepResult(x1, v1, a1, h, err))
        x1, v1, a1, err, extras = fused(raw.x, raw.v, raw.a, raw.error, raw.extras)
        return StepResult(x1, v1, a1, raw.h, err, None, extras)


def _read_stepper(solver) -> RungeKuttaStepper | None:
    tab = type(solver).tableau
    if getattr(tab, "implicit", False) or tab.b_error is None:
        return None
    a = tuple(tuple(float(v) for v in np.asarray(row)) for row in tab.a_lower)
    b = tuple(float(v) for v in np.asarray(tab.b_sol))
    e = tuple(float(v) for v in np.asarray(tab.b_error))
    c = tuple(float(v) for v in np.asarray(tab.c))
    fsal = bool(tab.fsal) and a[-1] == b[:-1] and c[-1] == 1.0
    order = float(solver.error_order(dfx.ODETerm(lambda t, y, args: y)))
    return RungeKuttaStepper(a, b, e, c, fsal, order)


_stepper_of = functools.lru_cache(maxsize=32)(_read_stepper)
