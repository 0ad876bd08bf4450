"""Type aliases of the public signatures.

Each is a `TypeAliasType` so that `help()` and `inspect.signature` print its name
(`L: Lagrangian, q0: Coordinates`) rather than the union or the jaxtyping form it
stands for."""

from collections.abc import Callable

from jaxtyping import Array, ArrayLike, Float


try:
    from typing import TypeAliasType
except ImportError:  # Python < 3.12
    from typing_extensions import TypeAliasType


RealScalarLike = TypeAliasType("RealScalarLike", float | int | ArrayLike)
Coordinates = TypeAliasType("Coordinates", Float[Array, " n"])
CoordinatesLike = TypeAliasType("CoordinatesLike", Float[ArrayLike, " n"])

# A Lagrangian `L(q, qdot, t) -> scalar`.
Lagrangian = TypeAliasType(
    "Lagrangian", Callable[[Coordinates, Coordinates, RealScalarLike], Array]
)
# A generalized non-conservative force `Q(q, qdot, t) -> (n,)`.
GeneralizedForce = TypeAliasType(
    "GeneralizedForce",
    Callable[[Coordinates, Coordinates, RealScalarLike], Coordinates],
)
