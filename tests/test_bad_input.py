"""Bad input at every public entry point: a clear TypeError/ValueError, eagerly.

Each case is one bad input. The error must be a `TypeError` or `ValueError` whose
message names the argument (in backticks), says what was expected ("must ...") and what
was received ("got ..." / "returned ..."), with no JAX tracer in it. Degenerate
Lagrangians raise eagerly and become a failure status per lane under `jit`/`vmap`.

Almost every case fails before anything is compiled, so the whole table is fast.
"""

import re

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import lagrax
from lagrax.systems import (
    charged_particle,
    cycloid,
    pendulum,
    rectilinear,
    sphere,
)


PENDULUM = pendulum.lagrangian()
Q1 = jnp.array([0.5])
V1 = jnp.array([0.1])
NAN = float("nan")
INF = float("inf")


def assert_clear(error, name, types=(TypeError, ValueError)):
    """The error is one of `types`, names `name`, says what it expected and got."""
    message = str(error)
    assert isinstance(error, types), f"{type(error).__name__}: {message}"
    assert f"`{name}`" in message, message
    assert re.search(r"\bmust\b|\bexpected\b", message), message
    assert re.search(r"\bgot\b|\breturned\b|\breceived\b|\bfailed\b", message), message
    assert "Tracer" not in message and "jaxpr" not in message, message


def case(id, thunk, name, *, xfail=None):
    marks = [pytest.mark.xfail(strict=True, reason=xfail)] if xfail else []
    return pytest.param(thunk, name, id=id, marks=marks)


# --------------------------------------------------------------------- bad values

# Lagrangians that are not Lagrangians.
BAD_L = {
    "float": 3.0,
    "str": "pendulum",
    "none": None,
    "vector": lambda q, qdot, t: q * qdot,
    "int": lambda q, qdot, t: 1,
    "complex": lambda q, qdot, t: (qdot[0] ** 2).astype(complex),
    "one-arg": lambda q: q[0] ** 2,
    "python-if": lambda q, qdot, t: qdot[0] ** 2 if q[0] > 0 else -(qdot[0] ** 2),
}

# (q, qdot) pairs, with the argument the error must name.
BAD_STATES = {
    "scalar-q": (jnp.array(0.5), jnp.array(0.1), "q"),
    "2d-q": (jnp.ones((1, 1)), V1, "q"),
    "2d-qdot": (Q1, jnp.ones((1, 1)), "qdot"),
    "length-mismatch": (jnp.ones(2), jnp.ones(3), "q"),
    "int-q": (jnp.array([1]), V1, "q"),
    "bool-qdot": (Q1, jnp.array([True]), "qdot"),
    "complex-q": (jnp.ones(1, complex), V1, "q"),
    "str-q": ("0.5", V1, "q"),
    "str-array-q": (np.array(["0.5"]), V1, "q"),
    "object-q": (object(), V1, "q"),
    "none-qdot": (Q1, None, "qdot"),
    "empty": (jnp.zeros(0), jnp.zeros(0), "q"),
    "nan-q": (jnp.array([NAN]), V1, "q"),
    "inf-qdot": (Q1, jnp.array([INF]), "qdot"),
}

BAD_TIMES = {
    "vector": jnp.ones(2),
    "str": "now",
    "complex": 1j,
    "nan": NAN,
    "none": None,
}

BAD_FORCES = {
    "not-callable": 1.0,
    "wrong-shape": lambda q, qdot, t: jnp.ones(2),
    "scalar": lambda q, qdot, t: q[0],
    "int": lambda q, qdot, t: jnp.ones(1, int),
    "one-arg": lambda q: q,
}

# Scalar options that must be positive and finite (tolerances, time limits).
BAD_POSITIVE = {
    "negative": -1e-8,
    "zero": 0.0,
    "nan": NAN,
    "inf": INF,
    "vector": jnp.ones(2),
    "str": "tight",
    "complex": 1e-8j,
}

BAD_COUNTS = {"zero": 0, "negative": -3, "float": 2.5, "str": "10", "bool": True}


# ------------------------------------------------------------------- mechanics

STATE_FUNCTIONS = {
    "accelerations": lagrax.accelerations,
    "mass_matrix": lagrax.mass_matrix,
    "momenta": lagrax.momenta,
    "energy": lagrax.energy,
}

MECHANICS = []
for fname, f in STATE_FUNCTIONS.items():
    for key, L in BAD_L.items():
        MECHANICS.append(case(f"{fname}-L-{key}", lambda f=f, L=L: f(L, Q1, V1), "L"))
    for key, (q, qdot, name) in BAD_STATES.items():
        MECHANICS.append(
            case(
                f"{fname}-{key}",
                lambda f=f, q=q, qdot=qdot: f(PENDULUM, q, qdot),
                name,
            )
        )
    for key, t in BAD_TIMES.items():
        MECHANICS.append(
            case(f"{fname}-t-{key}", lambda f=f, t=t: f(PENDULUM, Q1, V1, t), "t")
        )
for key, force in BAD_FORCES.items():
    MECHANICS.append(
        case(
            f"accelerations-force-{key}",
            lambda force=force: lagrax.accelerations(PENDULUM, Q1, V1, force=force),
            "force",
        )
    )
MECHANICS += [
    case("vector_field-L", lambda: lagrax.vector_field(3.0), "L"),
    case("vector_field-force", lambda: lagrax.vector_field(PENDULUM, force=2), "force"),
]


def test_shape_errors_are_clear_under_jit_and_vmap():
    # Shapes are known at trace time: the same clear error, not a tracer traceback.
    f = jax.jit(lambda q, qdot: lagrax.accelerations(PENDULUM, q, qdot))
    with pytest.raises(ValueError) as info:
        f(jnp.ones(2), jnp.ones(3))
    assert_clear(info.value, "q")
    g = jax.vmap(lambda q, qdot: lagrax.energy(PENDULUM, q, qdot))
    with pytest.raises(ValueError) as info:
        g(jnp.ones((4, 1, 1)), jnp.ones((4, 1, 1)))
    assert_clear(info.value, "q")
    h = jax.jit(lambda q: lagrax.momenta(PENDULUM, q, jnp.ones(1)))
    with pytest.raises(TypeError) as info:
        h(jnp.ones(1, int))
    assert_clear(info.value, "q")


# ------------------------------------------------------------------- simulate


def _simulate(**kw):
    args = dict(L=PENDULUM, q0=Q1, qdot0=V1, t0=0.0, t1=1.0)
    args.update(kw)
    return lagrax.simulate(**args)


SIMULATE = []
for key, L in BAD_L.items():
    SIMULATE.append(case(f"L-{key}", lambda L=L: _simulate(L=L), "L"))
for key, (q, qdot, name) in BAD_STATES.items():
    SIMULATE.append(
        case(key, lambda q=q, qdot=qdot: _simulate(q0=q, qdot0=qdot), name + "0")
    )
for which in ("t0", "t1", "dt0"):
    for key, t in BAD_TIMES.items():
        if which == "dt0" and t is None:
            continue  # dt0=None is the default
        SIMULATE.append(
            case(f"{which}-{key}", lambda w=which, t=t: _simulate(**{w: t}), which)
        )
for which in ("rtol", "atol"):
    for key, x in BAD_POSITIVE.items():
        SIMULATE.append(
            case(f"{which}-{key}", lambda w=which, x=x: _simulate(**{w: x}), which)
        )
for key, n in BAD_COUNTS.items():
    SIMULATE.append(
        case(f"max_steps-{key}", lambda n=n: _simulate(max_steps=n), "max_steps")
    )
for key, force in BAD_FORCES.items():
    SIMULATE.append(case(f"force-{key}", lambda f=force: _simulate(force=f), "force"))
SIMULATE += [
    case("solver-str", lambda: _simulate(solver="tsit5"), "solver"),
    case("solver-class", lambda: _simulate(solver=dfx.Tsit5), "solver"),
    case("fixed-step-without-dt0", lambda: _simulate(solver=dfx.Euler()), "dt0"),
    case("dt0-wrong-sign", lambda: _simulate(dt0=-0.1), "dt0"),
    case("dt0-zero", lambda: _simulate(solver=dfx.Euler(), dt0=0.0), "dt0"),
    case("backwards-dt0-positive", lambda: _simulate(t1=-1.0, dt0=0.1), "dt0"),
    case("saveat-list", lambda: _simulate(saveat=[0.0, 1.0]), "saveat"),
    case(
        "stepsize_controller-str",
        lambda: _simulate(stepsize_controller="pid"),
        "stepsize_controller",
    ),
    case(
        "event-callable",
        lambda: _simulate(event=lambda t, y, args, **kw: y[0][0]),
        "event",
    ),
]


SIMULATE = [p._replace(id=f"simulate-{p.id}") for p in SIMULATE]


# ------------------------------------------------------------------ periods

BAD_AMPLITUDES = {
    "int": (jnp.array([1]), TypeError),
    "complex": (jnp.array([1.0 + 0j]), TypeError),
    "str": ("1.0", TypeError),
    "none": (None, TypeError),
    "2d": (jnp.ones((2, 2)), ValueError),
}

PERIOD = []
for entry, f in (
    ("period", lagrax.period),
    ("sweep_periods", lagrax.sweep_periods),
    ("quadrature_period", lagrax.quadrature_period),
):
    one = jnp.array([1.0])
    for key, L in BAD_L.items():
        PERIOD.append(case(f"{entry}-L-{key}", lambda f=f, L=L: f(L, one), "L"))
    for key, (q0, _) in BAD_AMPLITUDES.items():
        if entry == "quadrature_period" and key == "2d":
            continue  # any shape is fine there
        PERIOD.append(
            case(f"{entry}-q0-{key}", lambda f=f, q0=q0: f(PENDULUM, q0), "q0")
        )
    for key, x in BAD_POSITIVE.items():
        PERIOD.append(
            case(
                f"{entry}-rtol-{key}", lambda f=f, x=x: f(PENDULUM, one, rtol=x), "rtol"
            )
        )
PERIOD += [
    case("period-q0-vector", lambda: lagrax.period(PENDULUM, jnp.ones(2)), "q0"),
    case("period-q0-nan", lambda: lagrax.period(PENDULUM, NAN), "q0"),
    case("period-q0-inf", lambda: lagrax.period(PENDULUM, -INF), "q0"),
    case(
        "sweep_periods-q0-empty",
        lambda: lagrax.sweep_periods(PENDULUM, jnp.zeros(0)),
        "q0",
    ),
    case("sweep_periods-q0-scalar", lambda: lagrax.sweep_periods(PENDULUM, 1.0), "q0"),
    case(
        "quadrature_period-q0-empty",
        lambda: lagrax.quadrature_period(PENDULUM, jnp.zeros((0, 3))),
        "q0",
    ),
    case(
        "quadrature_period-q0-nan",
        lambda: lagrax.quadrature_period(PENDULUM, jnp.array([1.0, NAN])),
        "q0",
    ),
    case(
        "period-L-two-dof",
        lambda: lagrax.period(lambda q, v, t: 0.5 * v @ v - 0.5 * q @ q, jnp.ones(2)),
        "q0",
    ),
    case(
        "period-solver-fixed-step",
        lambda: lagrax.period(PENDULUM, 1.0, solver=dfx.Euler()),
        "solver",
    ),
    case(
        "period-solver-implicit",
        lambda: lagrax.period(PENDULUM, 1.0, solver=dfx.Kvaerno5()),
        "solver",
    ),
    case(
        "period-solver-class",
        lambda: lagrax.period(PENDULUM, 1.0, solver=dfx.Dopri8),
        "solver",
    ),
    case(
        "period-solver-str",
        lambda: lagrax.period(PENDULUM, 1.0, solver="dopri8"),
        "solver",
    ),
    case(
        "period-method", lambda: lagrax.period(PENDULUM, 1.0, method="eighth"), "method"
    ),
    case(
        "period-method-none",
        lambda: lagrax.period(PENDULUM, 1.0, method=None),
        "method",
    ),
    case(
        "sweep_periods-devices-empty",
        lambda: lagrax.sweep_periods(PENDULUM, jnp.ones(1), devices=[]),
        "devices",
    ),
    case(
        "sweep_periods-devices-str",
        lambda: lagrax.sweep_periods(PENDULUM, jnp.ones(1), devices=["cpu"]),
        "devices",
    ),
    case(
        "sweep_periods-devices-one",
        lambda: lagrax.sweep_periods(PENDULUM, jnp.ones(1), devices=jax.devices()[0]),
        "devices",
    ),
    case(
        "sweep_periods-progress_meter",
        lambda: lagrax.sweep_periods(PENDULUM, jnp.ones(1), progress_meter=print),
        "progress_meter",
    ),
    case(
        "quadrature_period-nodes-odd",
        lambda: lagrax.quadrature_period(PENDULUM, 1.0, nodes=33),
        "nodes",
    ),
    case(
        "quadrature_period-inner_nodes-zero",
        lambda: lagrax.quadrature_period(PENDULUM, 1.0, inner_nodes=0),
        "inner_nodes",
    ),
    case("status_message-str", lambda: lagrax.status_message("success"), "code"),
    case("status_message-unknown", lambda: lagrax.status_message(99), "code"),
    case("status_message-float", lambda: lagrax.status_message(1.5), "code"),
    case("status_message-none", lambda: lagrax.status_message(None), "code"),
]
for entry, f in (("period", lagrax.period), ("sweep_periods", lagrax.sweep_periods)):
    for opt in ("atol", "t_max", "energy_tol"):
        for key in ("negative", "zero", "nan", "vector", "str"):
            x = BAD_POSITIVE[key]
            PERIOD.append(
                case(
                    f"{entry}-{opt}-{key}",
                    lambda f=f, o=opt, x=x: f(PENDULUM, jnp.ones(1), **{o: x}),
                    opt,
                )
            )
    for key, n in BAD_COUNTS.items():
        PERIOD.append(
            case(
                f"{entry}-max_steps-{key}",
                lambda f=f, n=n: f(PENDULUM, jnp.ones(1), max_steps=n),
                "max_steps",
            )
        )
for key, n in BAD_COUNTS.items():
    PERIOD.append(
        case(
            f"sweep_periods-lanes-{key}",
            lambda n=n: lagrax.sweep_periods(PENDULUM, jnp.ones(1), lanes=n),
            "lanes",
        )
    )
    PERIOD.append(
        case(
            f"quadrature_period-nodes-{key}",
            lambda n=n: lagrax.quadrature_period(PENDULUM, 1.0, nodes=n),
            "nodes",
        )
    )


# ------------------------------------------------- transforms, particles, solver

OTHER = [
    case("reparametrize-L", lambda: lagrax.reparametrize(3.0, lambda u, t: u), "L"),
    case("reparametrize-phi", lambda: lagrax.reparametrize(PENDULUM, "u"), "phi"),
]
for key, phi in {
    "wrong-length": lambda u, t: jnp.concatenate([u, u]),
    "2d": lambda u, t: u[None],
    "scalar": lambda u, t: u[0],
    "int": lambda u, t: jnp.ones(1, int),
    "one-arg": lambda u: u,
}.items():
    OTHER.append(
        case(
            f"reparametrize-phi-{key}",
            lambda phi=phi: lagrax.accelerations(
                lagrax.reparametrize(PENDULUM, phi), Q1, V1
            ),
            "phi",
        )
    )
OTHER += [
    case("LagrangianTerm-L", lambda: lagrax.LagrangianTerm("L"), "L"),
    case(
        "LagrangianTerm-force",
        lambda: lagrax.LagrangianTerm(PENDULUM, force=0.0),
        "force",
    ),
    case(
        "VariationalMidpoint-root_finder-str",
        lambda: lagrax.VariationalMidpoint(root_finder="newton"),
        "root_finder",
    ),
    case(
        "VariationalMidpoint-root_finder-minimiser",
        lambda: lagrax.VariationalMidpoint(root_finder=optx.BFGS(1e-8, 1e-8)),
        "root_finder",
    ),
    case(
        "VariationalMidpoint-root_find_max_steps-zero",
        lambda: lagrax.VariationalMidpoint(root_find_max_steps=0),
        "root_find_max_steps",
    ),
    case(
        "VariationalMidpoint-root_find_max_steps-float",
        lambda: lagrax.VariationalMidpoint(root_find_max_steps=2.5),
        "root_find_max_steps",
    ),
    case(
        "GaussLegendre4-root_finder",
        lambda: lagrax.GaussLegendre4(root_finder=1e-8),
        "root_finder",
    ),
    case(
        "GaussLegendre6-root_find_max_steps",
        lambda: lagrax.GaussLegendre6(root_find_max_steps=-1),
        "root_find_max_steps",
    ),
    case(
        "VariationalMidpoint-plain-ODETerm",
        lambda: dfx.diffeqsolve(
            dfx.ODETerm(lagrax.vector_field(PENDULUM)),
            lagrax.VariationalMidpoint(),
            0.0,
            1.0,
            0.1,
            (Q1, V1),
        ),
        "terms",
    ),
]


def _positions(q, t):
    return jnp.stack([jnp.sin(q[0]), -jnp.cos(q[0])])[None]


def _particle_L(positions=_positions, masses=jnp.array([1.0]), potential=None):
    L = lagrax.particle_lagrangian(masses, positions, potential)
    return lagrax.accelerations(L, Q1, V1)


SPHERE = lambda r, t: jnp.array([jnp.sum(r**2) - 1.0])
R_NORTH = jnp.array([[0.0, 0.0, 1.0]])

PARTICLES = [
    case("particle_lagrangian-masses-str", lambda: _particle_L(masses="1"), "masses"),
    case(
        "particle_lagrangian-masses-2d",
        lambda: _particle_L(masses=jnp.ones((1, 1))),
        "masses",
    ),
    case(
        "particle_lagrangian-masses-empty",
        lambda: _particle_L(masses=jnp.zeros(0)),
        "masses",
    ),
    case(
        "particle_lagrangian-masses-negative",
        lambda: _particle_L(masses=jnp.array([-1.0])),
        "masses",
    ),
    case(
        "particle_lagrangian-masses-nan",
        lambda: _particle_L(masses=jnp.array([NAN])),
        "masses",
    ),
    case(
        "particle_lagrangian-masses-complex",
        lambda: _particle_L(masses=jnp.array([1j])),
        "masses",
    ),
    case(
        "particle_lagrangian-positions",
        lambda: _particle_L(positions=None),
        "positions",
    ),
    case(
        "particle_lagrangian-potential", lambda: _particle_L(potential=2.0), "potential"
    ),
    case(
        "particle_lagrangian-positions-1d",
        lambda: _particle_L(positions=lambda q, t: _positions(q, t)[0]),
        "positions",
    ),
    case(
        "particle_lagrangian-positions-4d",
        lambda: _particle_L(positions=lambda q, t: jnp.ones((1, 4)) * q[0]),
        "positions",
    ),
    case(
        "particle_lagrangian-positions-count",
        lambda: _particle_L(positions=lambda q, t: jnp.ones((2, 2)) * q[0]),
        "positions",
    ),
    case(
        "particle_lagrangian-potential-vector",
        lambda: _particle_L(potential=lambda r, t: r[0]),
        "potential",
    ),
    case(
        "particle_lagrangian-positions-one-arg",
        lambda: _particle_L(positions=lambda q: _positions(q, 0.0)),
        "positions",
    ),
    case(
        "generalized_force-positions",
        lambda: lagrax.generalized_force(1.0, lambda r, v, t: v),
        "positions",
    ),
    case(
        "generalized_force-cartesian_force",
        lambda: lagrax.generalized_force(_positions, 1.0),
        "cartesian_force",
    ),
    case(
        "generalized_force-shape",
        lambda: lagrax.accelerations(
            PENDULUM,
            Q1,
            V1,
            force=lagrax.generalized_force(_positions, lambda r, v, t: v[0]),
        ),
        "cartesian_force",
    ),
    case("dissipation_force-R", lambda: lagrax.dissipation_force("R"), "R"),
    case(
        "dissipation_force-R-vector",
        lambda: lagrax.accelerations(
            PENDULUM, Q1, V1, force=lagrax.dissipation_force(lambda q, v, t: v)
        ),
        "R",
    ),
    case(
        "degrees_of_freedom-constraints",
        lambda: lagrax.degrees_of_freedom(None, R_NORTH),
        "constraints",
    ),
    case(
        "degrees_of_freedom-r-1d",
        lambda: lagrax.degrees_of_freedom(SPHERE, R_NORTH[0]),
        "r",
    ),
    case(
        "degrees_of_freedom-r-int",
        lambda: lagrax.degrees_of_freedom(SPHERE, jnp.array([[0, 0, 1]])),
        "r",
    ),
    case(
        "degrees_of_freedom-t-vector",
        lambda: lagrax.degrees_of_freedom(SPHERE, R_NORTH, jnp.ones(2)),
        "t",
    ),
    case(
        "degrees_of_freedom-rtol-negative",
        lambda: lagrax.degrees_of_freedom(SPHERE, R_NORTH, rtol=-1.0),
        "rtol",
    ),
    case(
        "degrees_of_freedom-constraints-2d",
        lambda: lagrax.degrees_of_freedom(lambda r, t: r, R_NORTH),
        "constraints",
    ),
    case(
        "check_embedding-q-2d",
        lambda: lagrax.check_embedding(sphere.positions(), SPHERE, jnp.ones((1, 2))),
        "q",
    ),
    case(
        "check_embedding-q-int",
        lambda: lagrax.check_embedding(sphere.positions(), SPHERE, jnp.array([1, 2])),
        "q",
    ),
    case(
        "check_embedding-positions",
        lambda: lagrax.check_embedding("r", SPHERE, jnp.ones(2)),
        "positions",
    ),
    case(
        "check_embedding-constraints",
        lambda: lagrax.check_embedding(sphere.positions(), 0, jnp.ones(2)),
        "constraints",
    ),
]

SYSTEMS = [
    case(
        "pendulum_period-str",
        lambda: pendulum.period("1.0"),
        "amplitude",
    ),
    case(
        "pendulum_period-complex",
        lambda: pendulum.period(1.0 + 0.5j),
        "amplitude",
    ),
    case(
        "rectilinear-potential",
        lambda: rectilinear.lagrangian(3.0),
        "potential",
    ),
    case(
        "charged_particle-B-shape",
        lambda: lagrax.accelerations(
            charged_particle.lagrangian(B=(1.0, 2.0)), jnp.ones(3), jnp.ones(3)
        ),
        "B",
    ),
    case(
        "cycloid_period-negative-R",
        lambda: cycloid.period(R=-1.0),
        "R",
    ),
]


@pytest.mark.parametrize(
    "thunk,name", MECHANICS + SIMULATE + PERIOD + OTHER + PARTICLES + SYSTEMS
)
def test_clear_error(thunk, name):
    with pytest.raises(Exception) as info:
        thunk()
    assert_clear(info.value, name)


# ------------------------------------------------------ degenerate Lagrangians


def _linear_in_qdot(q, qdot, t):
    return q[0] * qdot[0] - 0.5 * q[0] ** 2  # M = 0 everywhere


def _no_velocity(q, qdot, t):
    return -0.5 * q[0] ** 2  # M = 0 everywhere


def _indefinite(q, qdot, t):
    return 0.5 * (qdot[0] ** 2 - qdot[1] ** 2) - 0.5 * q @ q


def _rank_deficient(q, qdot, t):
    return 0.5 * (qdot[0] + qdot[1] + qdot[2]) ** 2 - 0.5 * q @ q  # M of rank 1


DEGENERATE = {
    "linear-in-qdot": (_linear_in_qdot, 1),
    "no-velocity": (_no_velocity, 1),
    "indefinite": (_indefinite, 2),
    "rank-deficient": (_rank_deficient, 3),
}


@pytest.mark.parametrize("key", list(DEGENERATE))
@pytest.mark.parametrize("entry", ["accelerations", "simulate"])
def test_degenerate_lagrangian_eager_error(key, entry):
    L, n = DEGENERATE[key]
    q, qdot = jnp.linspace(0.3, 0.6, n), jnp.linspace(-0.1, 0.2, n)
    with pytest.raises(ValueError, match=r"mass matrix M = ∂²L/∂qdot² is singular"):
        if entry == "accelerations":
            lagrax.accelerations(L, q, qdot)
        else:
            lagrax.simulate(L, q, qdot, 0.0, 1.0)


@pytest.mark.parametrize(
    "L", [_linear_in_qdot, pytest.param(_no_velocity, marks=pytest.mark.slow)]
)
def test_degenerate_lagrangian_period_eager_error(L):
    with pytest.raises(ValueError, match="`q0`.*singular_mass"):
        lagrax.period(L, 0.5)
    with pytest.raises(ValueError, match="q0=0.5"):
        lagrax.quadrature_period(L, 0.5)


def _mass_vanishing_at_2(q, qdot, t):
    # m(q) = (q - 2)²: singular only at q = 2; a harmonic well about 0.
    return 0.5 * (q[0] - 2.0) ** 2 * qdot[0] ** 2 - 0.5 * q[0] ** 2


def test_degenerate_lanes_fail_alone_under_jit_and_vmap():
    q = jnp.array([[2.0], [0.5], [1.0]])
    qdot = jnp.zeros((3, 1))
    acc = jax.jit(
        jax.vmap(lambda q, v: lagrax.accelerations(_mass_vanishing_at_2, q, v))
    )
    out = np.asarray(acc(q, qdot))
    assert np.isnan(out[0]).all() and np.isfinite(out[1:]).all()
    for i in (1, 2):
        np.testing.assert_array_equal(
            out[i], lagrax.accelerations(_mass_vanishing_at_2, q[i], qdot[i])
        )
    quad = lagrax.quadrature_period(_mass_vanishing_at_2, q[:, 0], throw=False)
    status = np.asarray(quad.status)
    assert status[0] != 0 and list(status[1:]) == [0, 0]
    assert np.isnan(quad.periods[0]) and np.isfinite(quad.periods[1:]).all()


def test_degenerate_simulate_lanes_report_failure():
    solve = jax.jit(
        jax.vmap(
            lambda q0: lagrax.simulate(
                _mass_vanishing_at_2, q0, jnp.zeros(1), 0.0, 2.0, throw=False
            )
        )
    )
    sol = solve(jnp.array([[2.0], [0.5], [1.0]]))
    ok = np.asarray(sol.result == dfx.RESULTS.successful)
    assert ok.tolist() == [False, True, True]
    assert np.isfinite(np.asarray(sol.ys[0][1:])).all()
    # throw=True under jit: an equinox runtime error, not a silent NaN.
    strict = jax.jit(
        lambda q0: lagrax.simulate(_mass_vanishing_at_2, q0, jnp.zeros(1), 0.0, 2.0)
    )
    with pytest.raises(Exception, match="minimum step size"):
        strict(jnp.array([2.0]))


def test_lagrangian_undefined_at_a_finite_state():
    L = lambda q, qdot, t: 0.5 * qdot[0] ** 2 - jnp.sqrt(q[0])  # NaN for q < 0
    with pytest.raises(ValueError, match="accelerations are not finite at q=\\[-1"):
        lagrax.accelerations(L, jnp.array([-1.0]), V1)


def test_period_warns_on_rtol_below_epsilon_before_compiling():
    with pytest.warns(UserWarning, match="machine epsilon"):
        with pytest.raises(ValueError, match="`method`"):
            lagrax.period(PENDULUM, 1.0, rtol=1e-17, method="eighth")


# ------------------------------------------------- exact messages, entry by entry

# Each case: (thunk, error type, regex the message must match). Moved here from the
# test files of each module, so that every bad-input test lives in one place.


def exact(id, thunk, error, match):
    return pytest.param(thunk, error, match, id=id)


def _pos1(q, t):
    return jnp.stack([jnp.sin(q[0]), -jnp.cos(q[0])])[None]


_q, _qdot = jnp.array([0.3]), jnp.array([0.1])
_m = jnp.array([1.0])
_one = jnp.ones(1)
_north = jnp.array([[0.0, 0.0, 1.0]])
_sphere = sphere.constraints()
_vector_positions = lambda q, t: jnp.stack([jnp.sin(q[0]), -jnp.cos(q[0])])
_wrong_force = lagrax.generalized_force(_pos1, lambda r, v, t: -v[0])
_doubled = lambda u, t: jnp.concatenate([u, u])
_CYCLOID = cycloid.lagrangian()


def _run(**kw):
    args = dict(q0=jnp.ones(1), qdot0=jnp.zeros(1), t0=0.0, t1=1.0)
    args.update(kw)
    return lagrax.simulate(PENDULUM, **args)


EXACT = [
    # accelerations
    exact(
        "acc-L",
        lambda: lagrax.accelerations(3.0, _one, _one),
        TypeError,
        "`L` must be a function",
    ),
    exact(
        "acc-L-vector",
        lambda: lagrax.accelerations(lambda q, v, t: q * v, jnp.ones(2), jnp.ones(2)),
        TypeError,
        r"`L` must return .*scalar.*shape \(2,\)",
    ),
    exact(
        "acc-q-0d",
        lambda: lagrax.accelerations(PENDULUM, jnp.array(0.5), jnp.array(0.5)),
        ValueError,
        r"`q` must be a 1-D array.*shape \(\)",
    ),
    exact(
        "acc-qdot-2d",
        lambda: lagrax.accelerations(PENDULUM, _one, jnp.ones((1, 1))),
        ValueError,
        r"`qdot` must be a 1-D",
    ),
    exact(
        "acc-length",
        lambda: lagrax.accelerations(PENDULUM, jnp.ones(2), jnp.ones(3)),
        ValueError,
        r"same length.*\(2,\).*\(3,\)",
    ),
    exact(
        "acc-q-int",
        lambda: lagrax.accelerations(PENDULUM, jnp.array([1]), jnp.array([0.0])),
        TypeError,
        "`q` must have a real floating dtype",
    ),
    exact(
        "acc-qdot-complex",
        lambda: lagrax.accelerations(PENDULUM, _one, jnp.ones(1, dtype=complex)),
        TypeError,
        "`qdot`.*complex",
    ),
    exact(
        "acc-force-shape",
        lambda: lagrax.accelerations(
            PENDULUM, _one, _one, force=lambda q, v, t: jnp.ones(2)
        ),
        TypeError,
        r"`force` must return .*shape \(1,\)",
    ),
    exact(
        "acc-force",
        lambda: lagrax.accelerations(PENDULUM, _one, _one, force=1.0),
        TypeError,
        "`force` must be a function",
    ),
    exact(
        "acc-q-nan",
        lambda: lagrax.accelerations(PENDULUM, jnp.array([jnp.nan]), _one),
        ValueError,
        "not finite",
    ),
    # simulate
    exact(
        "sim-q0-inf",
        lambda: _run(q0=jnp.array([jnp.inf])),
        ValueError,
        "`q0` must be finite",
    ),
    exact(
        "sim-qdot0-nan",
        lambda: _run(qdot0=jnp.array([jnp.nan])),
        ValueError,
        "`qdot0` must be finite",
    ),
    exact(
        "sim-length",
        lambda: _run(qdot0=jnp.zeros(2)),
        ValueError,
        "`q0` and `qdot0` must have the same",
    ),
    exact("sim-t1", lambda: _run(t1=jnp.ones(2)), ValueError, "`t1` must be a scalar"),
    exact(
        "sim-rtol", lambda: _run(rtol=-1e-6), ValueError, "`rtol` must be a positive"
    ),
    exact("sim-atol", lambda: _run(atol=0.0), ValueError, "`atol` must be a positive"),
    exact(
        "sim-euler",
        lambda: _run(solver=dfx.Euler()),
        ValueError,
        "`dt0` .*fixed-step solver Euler",
    ),
    exact(
        "sim-dt0-sign", lambda: _run(dt0=-0.1), ValueError, "`dt0` must have the sign"
    ),
    exact(
        "sim-singular",
        lambda: lagrax.simulate(lambda q, v, t: q[0] * v[0], _one, _one, 0.0, 1.0),
        ValueError,
        "singular",
    ),
    exact(
        "sim-solver",
        lambda: _run(solver="tsit5"),
        TypeError,
        "`solver` must be a diffrax solver",
    ),
    # period, sweep_periods
    exact("sweep-L", lambda: lagrax.sweep_periods("pendulum", _one), TypeError, "`L`"),
    exact(
        "sweep-q0-2d",
        lambda: lagrax.sweep_periods(PENDULUM, jnp.ones((2, 2))),
        ValueError,
        "`q0`",
    ),
    exact(
        "sweep-q0-int",
        lambda: lagrax.sweep_periods(PENDULUM, jnp.array([1, 2])),
        TypeError,
        "`q0`",
    ),
    exact(
        "sweep-rtol",
        lambda: lagrax.sweep_periods(PENDULUM, _one, rtol=-1.0),
        ValueError,
        "`rtol`",
    ),
    exact(
        "sweep-method",
        lambda: lagrax.sweep_periods(PENDULUM, _one, method="eighth"),
        ValueError,
        "`method`",
    ),
    exact(
        "sweep-chunk",
        lambda: lagrax.sweep_periods(PENDULUM, _one, lanes=0),
        ValueError,
        "`lanes`",
    ),
    exact(
        "sweep-euler",
        lambda: lagrax.sweep_periods(PENDULUM, _one, solver=dfx.Euler()),
        TypeError,
        "`solver`",
    ),
    exact(
        "period-q0-vector",
        lambda: lagrax.period(PENDULUM, jnp.array([1.0, 2.0])),
        ValueError,
        "`q0`",
    ),
    # quadrature_period
    exact(
        "quad-L", lambda: lagrax.quadrature_period("pendulum", 1.0), TypeError, "`L`"
    ),
    exact(
        "quad-q0-int",
        lambda: lagrax.quadrature_period(PENDULUM, jnp.array([1, 2])),
        TypeError,
        "`q0`",
    ),
    exact(
        "quad-q0-empty",
        lambda: lagrax.quadrature_period(PENDULUM, jnp.array([])),
        ValueError,
        "`q0`",
    ),
    exact(
        "quad-q0-nan",
        lambda: lagrax.quadrature_period(PENDULUM, jnp.array([1.0, jnp.nan])),
        ValueError,
        "`q0` must be finite",
    ),
    exact(
        "quad-nodes",
        lambda: lagrax.quadrature_period(PENDULUM, 1.0, nodes=33),
        ValueError,
        "`nodes`",
    ),
    exact(
        "quad-rtol",
        lambda: lagrax.quadrature_period(PENDULUM, 1.0, rtol=-1.0),
        ValueError,
        "`rtol`",
    ),
    exact(
        "quad-L-vector",
        lambda: lagrax.quadrature_period(lambda q, v, t: q, 1.0),
        TypeError,
        "one degree of freedom",
    ),
    # reparametrize
    exact(
        "phi-str",
        lambda: lagrax.reparametrize(_CYCLOID, "2 arccos u"),
        TypeError,
        "`phi`",
    ),
    exact(
        "phi-L", lambda: lagrax.reparametrize(None, lambda u, t: u), TypeError, "`L`"
    ),
    exact(
        "phi-length",
        lambda: lagrax.reparametrize(_CYCLOID, _doubled)(_q, _q, 0.0),
        ValueError,
        "same length",
    ),
    exact(
        "phi-scalar",
        lambda: lagrax.reparametrize(_CYCLOID, lambda u, t: u[0])(_q, _q, 0.0),
        ValueError,
        "1-D",
    ),
    exact(
        "phi-one-arg",
        lambda: lagrax.reparametrize(_CYCLOID, lambda u: u)(_q, _q, 0.0),
        TypeError,
        "phi\\(u, t\\)",
    ),
    exact(
        "phi-length-acc",
        lambda: lagrax.accelerations(lagrax.reparametrize(_CYCLOID, _doubled), _q, _q),
        ValueError,
        "same length",
    ),
    # particles
    exact(
        "masses-2d",
        lambda: lagrax.particle_lagrangian(jnp.array([[1.0]]), _pos1),
        ValueError,
        r"`masses` must be a 1-D array.*\(1, 1\)",
    ),
    exact(
        "masses-empty",
        lambda: lagrax.particle_lagrangian(jnp.zeros((0,)), _pos1),
        ValueError,
        r"`masses` must be a 1-D array.*\(0,\)",
    ),
    exact(
        "masses-0d",
        lambda: lagrax.particle_lagrangian(jnp.array(1.0), _pos1),
        ValueError,
        r"`masses`.*jnp.array\(\[m\]\)",
    ),
    exact(
        "masses-negative",
        lambda: lagrax.particle_lagrangian(jnp.array([1.0, -1.0]), _pos1),
        ValueError,
        "`masses` must be positive",
    ),
    exact(
        "masses-nan",
        lambda: lagrax.particle_lagrangian(jnp.array([jnp.nan]), _pos1),
        ValueError,
        "`masses` must be positive and finite",
    ),
    exact(
        "masses-str",
        lambda: lagrax.particle_lagrangian("heavy", _pos1),
        TypeError,
        "`masses`.*str",
    ),
    exact(
        "masses-complex",
        lambda: lagrax.particle_lagrangian(jnp.array([1.0 + 1j]), _pos1),
        TypeError,
        "`masses`.*complex",
    ),
    exact(
        "masses-none",
        lambda: lagrax.particle_lagrangian(None, _pos1),
        TypeError,
        "`masses`",
    ),
    exact(
        "positions-array",
        lambda: lagrax.particle_lagrangian(_m, jnp.zeros((1, 2))),
        TypeError,
        "`positions` must be a function",
    ),
    exact(
        "potential-float",
        lambda: lagrax.particle_lagrangian(_m, _pos1, 9.81),
        TypeError,
        "`potential` must be a function",
    ),
    exact(
        "positions-1d",
        lambda: lagrax.accelerations(
            lagrax.particle_lagrangian(_m, _vector_positions), _q, _qdot
        ),
        ValueError,
        r"`positions` must return.*\(N, d\).*r\[None\]",
    ),
    exact(
        "positions-4d",
        lambda: lagrax.particle_lagrangian(_m, lambda q, t: jnp.zeros((1, 4)) + q[0])(
            _q, _qdot, 0.0
        ),
        ValueError,
        r"`positions`.*d = 2 or 3.*\(1, 4\)",
    ),
    exact(
        "positions-count",
        lambda: lagrax.particle_lagrangian(jnp.array([1.0, 2.0]), _pos1)(
            _q, _qdot, 0.0
        ),
        ValueError,
        "`positions` returned 1 particles.*`masses` has 2",
    ),
    exact(
        "potential-vector",
        lambda: lagrax.particle_lagrangian(_m, _pos1, lambda r, t: r[0])(
            _q, _qdot, 0.0
        ),
        TypeError,
        r"`potential` must return a real.*scalar.*\(2,\)",
    ),
    # The checks fire at trace time, so under jit too.
    exact(
        "positions-1d-jit",
        lambda: jax.jit(lagrax.particle_lagrangian(_m, _vector_positions))(
            _q, _qdot, 0.0
        ),
        ValueError,
        "`positions` must return",
    ),
    exact(
        "cartesian_force-array",
        lambda: lagrax.generalized_force(_pos1, jnp.zeros((1, 2))),
        TypeError,
        "`cartesian_force` must be a function",
    ),
    exact(
        "generalized_force-positions",
        lambda: lagrax.generalized_force(None, lambda r, v, t: -v),
        TypeError,
        "`positions` must be a function",
    ),
    exact(
        "cartesian_force-shape",
        lambda: _wrong_force(_q, _qdot, 0.0),
        ValueError,
        r"`cartesian_force`.*\(1, 2\).*\(2,\)",
    ),
    # Through accelerations, the same message surfaces.
    exact(
        "cartesian_force-shape-acc",
        lambda: lagrax.accelerations(
            lagrax.particle_lagrangian(_m, _pos1), _q, _qdot, force=_wrong_force
        ),
        ValueError,
        "`cartesian_force` must return one force",
    ),
    exact(
        "R-float",
        lambda: lagrax.dissipation_force(0.5),
        TypeError,
        "`R` must be a Rayleigh function",
    ),
    exact(
        "R-vector",
        lambda: lagrax.dissipation_force(lambda q, qdot, t: 0.5 * qdot**2)(
            _q, _qdot, 0.0
        ),
        TypeError,
        r"`R` must return a real.*scalar.*\(1,\)",
    ),
    exact(
        "dof-r-1d",
        lambda: lagrax.degrees_of_freedom(_sphere, _north[0]),
        ValueError,
        r"`r` must be the particle positions.*\(3,\)",
    ),
    exact(
        "dof-r-4d",
        lambda: lagrax.degrees_of_freedom(_sphere, jnp.zeros((1, 4))),
        ValueError,
        r"`r` must be.*\(1, 4\)",
    ),
    exact(
        "dof-r-int",
        lambda: lagrax.degrees_of_freedom(_sphere, jnp.array([[0, 0, 1]])),
        TypeError,
        "`r` must have a real floating dtype",
    ),
    exact(
        "dof-constraints-str",
        lambda: lagrax.degrees_of_freedom("sphere", _north),
        TypeError,
        "`constraints` must be a function",
    ),
    exact(
        "dof-constraints-matrix",
        lambda: lagrax.degrees_of_freedom(
            lambda r, t: jnp.zeros((1, 1)) + jnp.sum(r**2) - 1.0, _north
        ),
        ValueError,
        r"`constraints` must return.*\(k,\).*\(1, 1\)",
    ),
    exact(
        "dof-t-vector",
        lambda: lagrax.degrees_of_freedom(_sphere, _north, jnp.zeros(2)),
        ValueError,
        "`t` must be a scalar",
    ),
    exact(
        "dof-rtol-zero",
        lambda: lagrax.degrees_of_freedom(_sphere, _north, rtol=0.0),
        ValueError,
        "`rtol` must be a positive",
    ),
    exact(
        "embedding-q-2d",
        lambda: lagrax.check_embedding(sphere.positions(), _sphere, jnp.zeros((1, 2))),
        ValueError,
        r"`q` must be a 1-D array.*\(1, 2\)",
    ),
    exact(
        "embedding-positions-1d",
        lambda: lagrax.check_embedding(
            lambda q, t: q, _sphere, jnp.array([0.1, 0.2, 0.3])
        ),
        ValueError,
        "`positions` must return",
    ),
]


@pytest.mark.parametrize("thunk,error,match", EXACT)
def test_exact_messages(thunk, error, match):
    with pytest.raises(error, match=match):
        thunk()


def test_simulate_warns_on_rtol_below_epsilon():
    with pytest.warns(UserWarning, match="machine epsilon") as record:
        _run(rtol=1e-17)
    assert record[0].filename == __file__  # points at the caller


# ------------------------------------------- out-of-range indexing in user functions


def _two_dof(q, qdot, t):  # written for two coordinates
    return 0.5 * (qdot[0] ** 2 + qdot[1] ** 2) - 0.5 * (q[0] ** 2 + 2 * q[1] ** 2)


def _pos_two(q, t):
    return jnp.stack([jnp.sin(q[1]), -jnp.cos(q[0])])[None]


INDEXING = [
    case("accelerations", lambda: lagrax.accelerations(_two_dof, Q1, V1), "L"),
    case("mass_matrix", lambda: lagrax.mass_matrix(_two_dof, Q1, V1), "L"),
    case("momenta", lambda: lagrax.momenta(_two_dof, Q1, V1), "L"),
    case("energy", lambda: lagrax.energy(_two_dof, Q1, V1), "L"),
    case(
        "accelerations-jit",
        lambda: jax.jit(lambda q: lagrax.accelerations(_two_dof, q, V1))(Q1),
        "L",
    ),
    case(
        "accelerations-vmap",
        lambda: jax.vmap(lambda q: lagrax.accelerations(_two_dof, q, q))(
            jnp.ones((3, 1))
        ),
        "L",
    ),
    case(
        "accelerations-force",
        lambda: lagrax.accelerations(PENDULUM, Q1, V1, force=lambda q, v, t: -v * v[1]),
        "force",
    ),
    case("simulate", lambda: lagrax.simulate(_two_dof, Q1, V1, 0.0, 1.0), "L"),
    case(
        "simulate-force",
        lambda: lagrax.simulate(
            PENDULUM, Q1, V1, 0.0, 1.0, force=lambda q, v, t: -q[1] * v
        ),
        "force",
    ),
    case("period", lambda: lagrax.period(_two_dof, 0.5), "L"),
    case("period-jit", lambda: jax.jit(lambda a: lagrax.period(_two_dof, a))(0.5), "L"),
    case("sweep_periods", lambda: lagrax.sweep_periods(_two_dof, jnp.ones(3)), "L"),
    case("quadrature_period", lambda: lagrax.quadrature_period(_two_dof, 0.5), "L"),
    case(
        "quadrature_period-vmap-closure",
        lambda: jax.vmap(
            lambda k: (
                lagrax.quadrature_period(
                    lambda q, v, t: _two_dof(q, v, t) * k, 0.5, throw=False
                ).periods
            )
        )(jnp.array([1.0, 2.0])),
        "<lambda>",
    ),
    case(
        "particle_lagrangian-positions",
        lambda: lagrax.accelerations(
            lagrax.particle_lagrangian(jnp.ones(1), _pos_two), Q1, V1
        ),
        "positions",
    ),
    case(
        "particle_lagrangian-potential",
        lambda: lagrax.accelerations(
            lagrax.particle_lagrangian(jnp.ones(1), _positions, lambda r, t: r[1, 1]),
            Q1,
            V1,
        ),
        "potential",
    ),
    case(
        "generalized_force-cartesian_force",
        lambda: lagrax.accelerations(
            PENDULUM,
            Q1,
            V1,
            force=lagrax.generalized_force(_positions, lambda r, v, t: -v * r[0, 2]),
        ),
        "cartesian_force",
    ),
    case(
        "dissipation_force-R",
        lambda: lagrax.simulate(
            PENDULUM,
            Q1,
            V1,
            0.0,
            1.0,
            force=lagrax.dissipation_force(lambda q, v, t: v[1] ** 2),
        ),
        "R",
    ),
    case(
        "degrees_of_freedom-constraints",
        lambda: lagrax.degrees_of_freedom(lambda r, t: r[1, :1], R_NORTH),
        "constraints",
    ),
    case(
        "check_embedding-positions",
        lambda: lagrax.check_embedding(
            lambda q, t: sphere.positions()(jnp.stack([q[0], q[2]]), t),
            SPHERE,
            jnp.array([0.3, 0.2]),
        ),
        "positions",
    ),
    case(
        "reparametrize-phi",
        lambda: lagrax.accelerations(
            lagrax.reparametrize(PENDULUM, lambda u, t: u * u[1]), Q1, V1
        ),
        "phi",
    ),
]


@pytest.mark.parametrize("thunk,name", INDEXING)
def test_out_of_range_index_is_an_error(thunk, name):
    with pytest.raises(ValueError) as info:
        jax.block_until_ready(thunk())
    if name != "<lambda>":
        assert_clear(info.value, name)
    message = str(info.value)
    assert "must index its arguments within their shapes" in message
    assert "out-of-bounds" in message
    # Where: this file, the line that indexes.
    assert "test_bad_input.py:" in message


def test_sweep_of_a_two_coordinate_lagrangian_is_not_a_number():
    # Before the check: periods 5.99... with status success (q[1] read q[0]).
    with pytest.raises(ValueError, match=r"index 1 is out of bounds.*`L2 = "):
        L2 = lambda q, qdot, t: 0.5 * qdot[0] ** 2 + 0.5 * qdot[1] ** 2 - q[1] ** 2
        lagrax.sweep_periods(L2, jnp.array([0.5, 1.0]))


def test_indexing_within_range_is_fine():
    # Negative indices, slices, explicit clipping and the right number of coordinates.
    L = lambda q, qdot, t: (
        0.5 * qdot[-1] ** 2
        - 0.5 * jnp.sum(q[:5] ** 2)
        + 0 * jnp.take(q, 3, mode="clip")
    )
    np.testing.assert_allclose(lagrax.accelerations(L, Q1, V1), -Q1)
    two = jnp.array([0.5, 0.2])
    np.testing.assert_allclose(
        lagrax.accelerations(_two_dof, two, two), jnp.array([-0.5, -0.4])
    )
    assert np.isfinite(lagrax.period(lambda q, v, t: L(q, v, t) - q[0] ** 4, 0.5))


def test_index_check_adds_nothing_to_the_computation():
    checked = jax.make_jaxpr(lambda q, v: lagrax.accelerations(PENDULUM, q, v))(Q1, V1)
    # Traced, `accelerations` runs the equations' program inline (no nested jit).
    core = jax.make_jaxpr(
        lambda q, v: lagrax._eom.mechanics._accelerations(
            PENDULUM, q, v, jnp.zeros(()), None
        )[0]
    )(Q1, V1)
    assert str(checked) == str(core)


def _fancy(q, qdot, t):
    return 0.5 * jnp.sum(qdot[jnp.array([0, 1])] ** 2) - 0.5 * q[0] ** 2


def test_fancy_index_out_of_range():
    # A gather (not a slice): reported too, naming `L`, at every call.
    for _ in range(2):
        with pytest.raises(ValueError, match="`L` must index its arguments") as info:
            lagrax.accelerations(_fancy, Q1, V1)
        assert_clear(info.value, "L")
    np.testing.assert_allclose(
        lagrax.accelerations(_fancy, jnp.array([0.5, 0.0]), jnp.zeros(2)), [-0.5, 0.0]
    )
