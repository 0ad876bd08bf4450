import importlib.metadata

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
    quadrature_status_message as quadrature_status_message,
    QuadratureResult as QuadratureResult,
)
from ._period.sweep import sweep_periods as sweep_periods, SweepResult as SweepResult
from ._results import (
    RESULTS as RESULTS,
    status_code as status_code,
    STATUS_CODES as STATUS_CODES,
    status_message as status_message,
    status_result as status_result,
)
from ._taylor.coefficients import Taylor as Taylor
from ._trajectory.batch import simulate_batch as simulate_batch
from ._trajectory.gauss_legendre import (
    GaussLegendre4 as GaussLegendre4,
    GaussLegendre6 as GaussLegendre6,
)
from ._trajectory.simulate import simulate as simulate, vector_field as vector_field
from ._trajectory.term import LagrangianTerm as LagrangianTerm
from ._trajectory.variational import VariationalMidpoint as VariationalMidpoint


__version__ = importlib.metadata.version("lagrax")
