import importlib.metadata

from . import systems as systems
from ._mechanics import (
    accelerations as accelerations,
    energy as energy,
    mass_matrix as mass_matrix,
    momenta as momenta,
)
from ._simulate import simulate as simulate, vector_field as vector_field
from ._transform import reparametrize as reparametrize
from ._variational import (
    LagrangianTerm as LagrangianTerm,
    VariationalMidpoint as VariationalMidpoint,
)


__version__ = importlib.metadata.version("lagrax")
