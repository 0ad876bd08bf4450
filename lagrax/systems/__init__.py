"""Ready-made Lagrangians, each with its exact references.

Every module here has the same shape:

- `lagrangian(**params)` returns a plain `L(q, qdot, t)`; every parameter is a keyword
    with a default (`rectilinear`'s `potential` is a function, default `harmonic`);
- `acceleration(q, qdot, t=0.0, **params)`: the hand-derived equation of motion,
    $\\ddot q$ of shape `(n,)`, the same parameters (those that do not enter, such as
    a pendulum's mass, are accepted and ignored);
- `period(amplitude, **params)` where the period is known in closed form (`pendulum`,
    `cycloid`);
- `force(**params)` where the system has a non-conservative force
    (`damped_pendulum`): then `acceleration` solves Lagrange's equations with it;
- `small_amplitude_period(**params)` where the limit of the period at small
    amplitudes is known in closed form;
- `SWEEP`, a `SweepSpec`, where `lagrax sweep NAME` needs more than the release
    point $q_0$ as the amplitude (its symbol, default range, method, coordinate).

`parameters(module)` lists a system's parameters and their defaults.
"""

import inspect as _inspect

from . import (
    asymmetric_well as asymmetric_well,
    charged_particle as charged_particle,
    cycloid as cycloid,
    damped_pendulum as damped_pendulum,
    double_pendulum as double_pendulum,
    driven_pendulum as driven_pendulum,
    pendulum as pendulum,
    rectilinear as rectilinear,
    rotating_hoop as rotating_hoop,
    sphere as sphere,
    spherical_pendulum as spherical_pendulum,
)
from ._sweep_spec import SweepSpec as SweepSpec


#: Every built-in system, by name.
SYSTEMS = {
    module.__name__.rsplit(".", 1)[-1]: module
    for module in (
        asymmetric_well,
        charged_particle,
        cycloid,
        damped_pendulum,
        double_pendulum,
        driven_pendulum,
        pendulum,
        rectilinear,
        rotating_hoop,
        sphere,
        spherical_pendulum,
    )
}


def parameters(system) -> dict:
    """The parameters of a built-in system and their defaults, `{name: default}`: the
    keywords of its `lagrangian` and, where it has one, of its `force`.

    **Arguments:** `system`: a module of `lagrax.systems` or its name.

    **Raises:** `ValueError` for an unknown name.
    """
    if isinstance(system, str):
        if system not in SYSTEMS:
            raise ValueError(
                f"`system` must be one of {sorted(SYSTEMS)}; got {system!r}."
            )
        system = SYSTEMS[system]
    functions = [system.lagrangian] + (
        [system.force] if hasattr(system, "force") else []
    )
    return {
        name: p.default
        for f in functions
        for name, p in _inspect.signature(f).parameters.items()
    }
