from collections.abc import Callable
from typing import TypeAlias

from jaxtyping import Array, ArrayLike, Float


RealScalarLike: TypeAlias = float | int | ArrayLike
Coordinates: TypeAlias = Float[Array, " n"]
CoordinatesLike: TypeAlias = Float[ArrayLike, " n"]

# A Lagrangian `L(q, qdot, t) -> scalar`.
Lagrangian: TypeAlias = Callable[[Coordinates, Coordinates, RealScalarLike], Array]
# A generalized non-conservative force `Q(q, qdot, t) -> (n,)`.
GeneralizedForce: TypeAlias = Callable[
    [Coordinates, Coordinates, RealScalarLike], Coordinates
]
