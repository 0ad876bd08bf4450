"""The arguments `period` and `sweep_periods` share, checked once per call."""

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from .._checks import (
    check_choice,
    check_instance,
    check_one_dof,
    describe,
    is_concrete,
    positive_int,
    positive_scalar,
    tolerances,
)
from .._taylor.taylor import Taylor
from .solver import stepper_of


METHODS = ("matched", "half", "full", "quarter")


class Options(eqx.Module):
    rtol: Array
    atol: Array
    t_max: Array | None
    energy_tol: Array | None
    max_steps: int = eqx.field(static=True)
    method: str = eqx.field(static=True)


def check_options(
    L, dtype, solver, rtol, atol, t_max, energy_tol, max_steps, method
) -> Options:
    """The checks `period` and `sweep_periods` share (called by them directly: the
    tolerance warnings point at their caller)."""
    check_one_dof(L, dtype)
    check_instance(
        solver,
        "solver",
        (dfx.AbstractERK, Taylor),
        "an adaptive explicit Runge–Kutta diffrax solver (the period kernel steps "
        "through its Butcher tableau), e.g. diffrax.Dopri8() or diffrax.Tsit5(), or "
        "lagrax.Taylor()",
    )
    if stepper_of(solver) is None:
        raise TypeError(
            "`solver` must be an adaptive explicit Runge–Kutta diffrax solver (with an "
            f"embedded error estimate), e.g. diffrax.Dopri8(); got {describe(solver)}."
        )
    _check_precision(positive_scalar(rtol, "rtol", dtype), dtype)
    rtol, atol = tolerances(rtol, atol, dtype, stacklevel=3)
    return Options(
        rtol,
        atol,
        positive_scalar(t_max, "t_max", dtype, optional=True),
        positive_scalar(energy_tol, "energy_tol", dtype, optional=True),
        positive_int(max_steps, "max_steps"),
        check_choice(method, "method", METHODS),
    )


def _check_precision(rtol, dtype):
    """Every lane fails when `rtol` is finer than a float32 state can resolve, with a
    status that blames the orbit: say float32 instead, and how to get float64."""
    finfo = jnp.finfo(dtype)
    if finfo.bits < 64 and is_concrete(rtol) and float(rtol) < float(finfo.eps):
        raise ValueError(
            f"`rtol` must be at least the machine epsilon of the release points' "
            f"dtype; got rtol={float(rtol):g} with {jnp.dtype(dtype).name} release "
            f"points (epsilon {float(finfo.eps):.2g}): no lane can reach it. JAX "
            "computes in float32 unless its 64-bit mode is on: add "
            '`jax.config.update("jax_enable_x64", True)` at the start of the program '
            f"(before any array is made), or pass rtol >= {float(finfo.eps):.2g}."
        )
