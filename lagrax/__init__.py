"""Lagrangian mechanics by automatic differentiation, on JAX and diffrax.

Write a Lagrangian as a plain JAX function `L(q, qdot, t) -> scalar` (parameters by
closure); lagrax derives Lagrange's equations by autodiff,

    M q̈ = ∂L/∂q − (∂²L/∂q̇∂q) q̇ − ∂²L/∂q̇∂t + Q,   M = ∂²L/∂q̇²,

and integrates them, one state or many at once.

- Equations of motion: `accelerations`, `mass_matrix`, `momenta`, `energy`,
    `vector_field`; from particle positions and constraints: `particle_lagrangian`,
    `generalized_force`, `dissipation_force`, `degrees_of_freedom`,
    `check_embedding`; a change of coordinates: `reparametrize`.
- Trajectories: `simulate` (one release, through `diffrax.diffeqsolve`),
    `simulate_batch` (many releases in one compiled loop), or `LagrangianTerm` with
    the variational integrators `VariationalMidpoint`, `GaussLegendre4`,
    `GaussLegendre6`; the Taylor integrator `Taylor` is a diffrax solver.
- Periods of one-coordinate oscillations: `period` (one amplitude),
    `sweep_periods` (many at once, a `SweepResult`), the oracle `quadrature_period`
    (a `QuadratureResult`).
- Statuses of a period: the enumeration `PeriodStatus` (as `diffrax.RESULTS` is
    for a solve) and its int codes, as `SweepResult.status` holds them:
    `STATUS_CODES`, `status_code`, `status_member`, `status_message`.
- `lagrax.systems`: ready-made Lagrangians with their exact references.

lagrax never changes JAX's configuration: for float64, where accuracy is claimed, call
`jax.config.update("jax_enable_x64", True)` at the start of the program. The command
line `lagrax sweep` (`python -m lagrax sweep --help`) sweeps periods against amplitude.
"""

import importlib.metadata as _metadata

from . import systems as systems
from ._eom.mechanics import (
    accelerations as accelerations,
    energy as energy,
    mass_matrix as mass_matrix,
    momenta as momenta,
)
from ._eom.particles import (
    check_embedding as check_embedding,
    degrees_of_freedom as degrees_of_freedom,
    dissipation_force as dissipation_force,
    generalized_force as generalized_force,
    particle_lagrangian as particle_lagrangian,
)
from ._eom.reparametrize import reparametrize as reparametrize
from ._period.period import period as period
from ._period.quadrature import (
    quadrature_period as quadrature_period,
    QuadratureResult as QuadratureResult,
)
from ._period.sweep import sweep_periods as sweep_periods, SweepResult as SweepResult
from ._results import (
    PeriodStatus as PeriodStatus,
    status_code as status_code,
    STATUS_CODES as STATUS_CODES,
    status_member as status_member,
    status_message as status_message,
)
from ._taylor.taylor import Taylor as Taylor
from ._trajectory.batch import simulate_batch as simulate_batch
from ._trajectory.gauss_legendre import (
    GaussLegendre4 as GaussLegendre4,
    GaussLegendre6 as GaussLegendre6,
)
from ._trajectory.simulate import simulate as simulate, vector_field as vector_field
from ._trajectory.term import LagrangianTerm as LagrangianTerm
from ._trajectory.variational import VariationalMidpoint as VariationalMidpoint


try:
    __version__ = _metadata.version("lagrax")
except _metadata.PackageNotFoundError:  # a source tree on sys.path, not installed
    __version__ = "0+unknown"
