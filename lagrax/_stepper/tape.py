r"""The Taylor step with its coefficients from a tape (`lagrax._taylor.tape`).

The same step as `TaylorStepper` (length rule, polynomials, event inside the step),
its coefficients computed by one fixed interpreter from the acceleration's tape,
which the `LaneField` carries as its `scalar_accel` (a `TapeAccel`, with the
Lagrangian's parameters): the compiled step is the same for every Lagrangian.
"""

import jax.numpy as jnp

from .._taylor.tape import tape_coefficients
from .taylor import TaylorStepper


class TapeTaylorStepper(TaylorStepper):
    """`TaylorStepper` reading the acceleration from a tape (`field.scalar_accel`:
    an object with `.tape` and `.params`)."""

    def coefficients(self, field, s, x, v):
        accel = field.scalar_accel
        W = x.shape[0]
        lanes = [jnp.broadcast_to(p, (W,)) for p in (*field.params, *accel.params)]
        xs, vs, as_ = tape_coefficients(
            accel.tape, self.order, s, x, v, lanes, trig=True
        )
        return list(xs), list(vs), list(as_)
