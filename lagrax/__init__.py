import importlib.metadata

from . import systems as systems
from ._gauss_legendre import (
    GaussLegendre4 as GaussLegendre4,
    GaussLegendre6 as GaussLegendre6,
)
from ._mechanics import (
    accelerations as accelerations,
    energy as energy,
    mass_matrix as mass_matrix,
    momenta as momenta,
)
from ._particles import (
    check_embedding as check_embedding,
    degrees_of_freedom as degrees_of_freedom,
    dissipation_force as dissipation_force,
    generalized_force as generalized_force,
    particle_lagrangian as particle_lagrangian,
)
from ._period import period as period
from ._quadrature import (
    quadrature_period as quadrature_period,
    quadrature_status_message as quadrature_status_message,
    QuadratureResult as QuadratureResult,
)
from ._results import (
    RESULTS as RESULTS,
    status_code as status_code,
    STATUS_CODES as STATUS_CODES,
    status_message as status_message,
    status_result as status_result,
)
from ._simulate import simulate as simulate, vector_field as vector_field
from ._sweep import sweep_periods as sweep_periods, SweepResult as SweepResult
from ._taylor import Taylor as Taylor
from ._term import LagrangianTerm as LagrangianTerm
from ._transform import reparametrize as reparametrize
from ._variational import VariationalMidpoint as VariationalMidpoint


__version__ = importlib.metadata.version("lagrax")
