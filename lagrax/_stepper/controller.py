r"""The step-size controller: diffrax's I-controller rule with its default constants.

$$h_\text{next} = h\,\operatorname{clip}\left(\text{safety}\cdot
\text{err}^{-1/k},\ f_\text{min},\ f_\text{max}\right),$$

with $k$ the stepper's error order, the clip range $[1, f_\text{max}]$ after an
accepted step and $[f_\text{min}, \text{safety}]$ after a rejected one, as
`diffrax.PIDController` does with its default coefficients (which are read from it).
"""

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .base import AbstractStepper


def _root(x, n):
    """`x ** (1 / n)`; by nested square roots where `n` is a power of two (Dopri8:
    n = 8). XLA's CPU backend calls the C library's scalar `pow` once per lane, while
    `sqrt` is vectorized and correctly rounded, so every lane gets the same bits
    whatever its position in the vector (`exp2(log2(x) / n)` does not: its vector and
    scalar code paths differ in the last bit)."""
    k = int(n)
    if k == n and k >= 1 and k & (k - 1) == 0:
        for _ in range(k.bit_length() - 1):
            x = jnp.sqrt(x)
        return x
    return x ** (1.0 / n)


class IController(eqx.Module):
    """diffrax's I-controller (`diffrax.PIDController`'s rule and default constants)."""

    safety: float = eqx.field(static=True)
    factormin: float = eqx.field(static=True)
    factormax: float = eqx.field(static=True)

    def __init__(self):
        defaults = dfx.PIDController(rtol=0.0, atol=0.0)
        self.safety = defaults.safety
        self.factormin = defaults.factormin
        self.factormax = defaults.factormax

    def initial_step(self, stepper: AbstractStepper, rtol, atol, dtype):
        """A first step length from the tolerances (in the lane's units of time)."""
        expo = 1.0 / stepper.error_order
        return 0.1 * jnp.minimum(rtol, atol).astype(dtype) ** expo

    def adapt(self, stepper: AbstractStepper, h, error, finite, accept):
        """The next step length after a step of length `h` with error ratio `error`
        (`finite`: lanes whose step gave finite numbers; `accept`: those accepted).
        A failed step gives a length below any usable one."""
        if not stepper.rejects:
            # The error ratio is 0 or NaN: the factor is a constant, without a `pow`
            # per lane (a libm call on a CPU).
            grow = self.safety * 1e10 ** (1.0 / stepper.error_order)
            factor = jnp.where(finite, float(np.clip(grow, 1.0, self.factormax)), 0.0)
        else:
            grows = finite & (error > 0)
            inv = jnp.where(grows, 1.0 / jnp.where(error > 0, error, 1.0), 1e10)
            factor = jnp.clip(
                self.safety * _root(inv, stepper.error_order),
                jnp.where(accept, 1.0, self.factormin),
                jnp.where(accept, self.factormax, self.safety),
            )
            factor = jnp.where(finite, factor, self.factormin)
        return jax.lax.stop_gradient(h * factor)
