r"""The Taylor step with its coefficients from a compact tape (`lagrax._taylor`).

The same step as `TaylorStepper` (length rule, polynomials, event inside the step),
its coefficients computed by the compact coefficient program from the step tape of
$x'' = a(s, x, v)$, which the `LaneField` carries as its `scalar_accel` (a
`CompactAccel`, with the Lagrangian's parameters): the compiled step is the same
for every Lagrangian of the tape's size class.
"""

import jax.numpy as jnp

from .compact import compact_coefficients
from .stepper import TaylorStepper


class CompactTaylorStepper(TaylorStepper):
    """`TaylorStepper` reading the acceleration from a compact tape
    (`field.scalar_accel`: an object with `.tape` and `.params`)."""

    def fuses_by_select(self, field, dtype) -> bool:
        # (The compact program reads its tape: no transcendental of L's own.)
        return self.branch_free

    def coefficients(self, field, s, x, v):
        accel = field.scalar_accel
        W = x.shape[0]
        lanes = [jnp.broadcast_to(p, (W,)) for p in (*field.params, *accel.params)]
        xs, vs = compact_coefficients(
            accel.tape, self.order, s, [x, v], lanes, trig=True
        )
        # (a_k = (k + 1) v_{k+1}: the tape's outputs are v' = a.)
        return list(xs), list(vs), [(k + 1) * vs[k + 1] for k in range(self.order)]
