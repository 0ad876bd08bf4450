"""The period sweep's tiers (`lagrax._period.tier`): the compact program, L as data,
against the specialized one; sizes padded to classes; the rule that picks a tier."""

import collections

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax._cache import executables
from lagrax._jaxpr.canonical import canonical_lagrangian
from lagrax._period import sweep as sweep_module, tier
from lagrax._period.quantities import AutodiffMechanics, CompactMechanics
from lagrax._period.units import Release
from lagrax._taylor.stepper import TaylorStepper
from lagrax.systems import asymmetric_well, cycloid, pendulum, rectilinear


# A cheap program to compile: Tsit5, a quarter swing, no error estimate.
CHEAP = dict(solver=dfx.Tsit5(), method="quarter", error_estimate=False)


def _time_dependent(q, qdot, t):
    """A mass that varies, a velocity term and explicit time: every term of the
    point tape (the jerk's ∂t, the energy's ∂L/∂q̇) is exercised."""
    M = 1.0 + 0.3 * q[0] ** 2
    return (
        0.5 * M * qdot[0] ** 2 - 2 * jnp.sin(q[0] / 2) ** 2 + 0.1 * t * q[0] * qdot[0]
    )


@pytest.mark.parametrize("n", [1, 7, 8, 9, 12, 13, 100, 1000, 2000, 2001, 4096])
def test_size_classes_hold_the_count_within_a_third(n):
    size = sweep_module.size_class(n)
    assert size >= max(n, 8)
    k = size.bit_length() - 1
    assert size in (1 << k, 3 << (k - 1))  # a power of two, or 1.5 times one
    assert size <= max(8, 4 * n / 3 + 1)
    assert sweep_module.size_class(size) == size


def test_a_count_in_the_same_size_class_compiles_nothing():
    compiles = []

    def listen(event, seconds, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(seconds)

    jax.monitoring.register_event_duration_secs_listener(listen)
    L = pendulum.lagrangian(g=1.7)
    q0 = np.linspace(0.2, 2.9, 11)
    q10, q11 = jnp.asarray(q0[:10]), jnp.asarray(q0)
    first = lagrax.sweep_periods(L, q10, **CHEAP)
    before = len(compiles)
    second = lagrax.sweep_periods(L, q11, **CHEAP)  # (both of class 12)
    assert len(compiles) == before
    assert first.periods.shape == (10,) and second.periods.shape == (11,)
    # Padding changes nothing: the lanes are independent.
    np.testing.assert_array_equal(first.periods, second.periods[:10])
    np.testing.assert_array_equal(first.num_steps, second.num_steps[:10])
    assert int(second.lane_steps_useful) == int(np.sum(second.num_steps))
    np.testing.assert_allclose(second.periods, pendulum.period(q0, g=1.7), rtol=1e-8)


def _points(dtype):
    q = jnp.array([0.3, -1.1, 2.0], dtype)
    qdot = jnp.array([0.5, 0.0, -0.7], dtype)
    t = jnp.array([0.0, 1.5, -0.4], dtype)
    return q, qdot, t


def _quantities(mech, q, qdot, t):
    """Everything the period program reads of L, per lane (vmapped)."""
    one = lambda u: jnp.reshape(u, (1,))
    rel = Release(
        q, q > 0, q > 0, q > 0, q > 0, 1.0 + q**2, -jnp.ones_like(q), 1.0 + 0 * q,
        1.3 + 0 * q, -jnp.ones_like(q),
    )  # fmt: skip

    def lane(q, qdot, t, r):
        (a, (M, ok)), (h, size) = mech.point(one(q), one(qdot), t)
        start, end = mech.rest_and_end(q, q + 0.2, qdot, t)
        a_e, jerk = mech.end_accel_and_jerk(r, t, q, qdot)
        ahead, behind = mech.end_accels(r, [(t, q, qdot), (t + 0.1, q, -qdot)])
        L, slope = mech.rest_value_and_slope(q.dtype)(q)
        scaled = mech.scaled_acceleration()(q, 1.3, 0.7, t, q, qdot)
        return (a[0], M[0, 0], ok, h, size, start, end[1], a_e, jerk, ahead, behind,
                L, slope, scaled, mech.value(one(q), one(qdot), t))  # fmt: skip

    return jax.vmap(lane)(q, qdot, t, rel)


def test_the_compact_tapes_give_what_autodiff_gives():
    dtype = jnp.float64
    L_c, consts = canonical_lagrangian(_time_dependent, dtype)
    L_t, tapes = tier.tapes_of(L_c, consts, dtype)
    params = [jnp.asarray(c, dtype).reshape(()) for c in consts]
    params += [jnp.zeros((), dtype)] * (L_t.n_params - len(params))
    q, qdot, t = _points(dtype)

    @jax.jit
    def both(q, qdot, t):
        compact = CompactMechanics(L_t, [tapes, *params])
        return (
            _quantities(compact, q, qdot, t),
            _quantities(AutodiffMechanics(L_c, list(consts)), q, qdot, t),
            # Forward mode through the compact tapes (the periods' tangents).
            jax.jvp(lambda q: _quantities(compact, q, qdot, t)[7:9], (q,), (q,)),
            jax.jvp(
                lambda q: _quantities(AutodiffMechanics(L_c, consts), q, qdot, t)[7:9],
                (q,),
                (q,),
            ),
        )

    got, want, d_got, d_want = both(q, qdot, t)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-14),
                 (got, d_got), (want, d_want))  # fmt: skip
    # The natural systems share one size class (one executable).
    sizes = {
        tier.tapes_of(*canonical_lagrangian(L, dtype), dtype)[0]
        for L in (pendulum.lagrangian(g=3.0), asymmetric_well.lagrangian(),
                  cycloid.lagrangian(), rectilinear.lagrangian())
    }  # fmt: skip
    assert len(sizes) == 1


def _power_well_tapes(dtype):
    """The compact tapes of V = (1 + q)^1.5 (V'' infinite at q = -1) and its
    parameters padded to the tapes' count: `(L_c, consts, L_t, tapes, params)`."""
    L = lambda q, qdot, t: 0.5 * qdot[0] ** 2 - (1.0 + q[0]) ** 1.5
    L_c, consts = canonical_lagrangian(L, dtype)
    L_t, tapes = tier.tapes_of(L_c, consts, dtype)
    params = [jnp.asarray(c, dtype).reshape(()) for c in consts]
    params += [jnp.zeros((), dtype)] * (L_t.n_params - len(params))
    return L_c, consts, L_t, tapes, params


def test_the_compact_leg_ends_give_what_autodiff_gives():
    # `leg_ends` evaluates the point tape at one site for the ends of the legs and,
    # where a jerk is not finite (V = (1 + q)^1.5 has V'' infinite at -1: the middle
    # lane ends there, at rest), for the central difference's accelerations too.
    from lagrax._period.finish import _central_points

    dtype = jnp.float64
    L_c, consts, L_t, tapes, params = _power_well_tapes(dtype)
    q0 = jnp.array([0.3, 0.5, -1.1], dtype)
    rel = Release(
        q0, q0 > -2, q0 > -2, q0 > -2, q0 > -2, jnp.ones_like(q0), -jnp.ones_like(q0),
        jnp.ones_like(q0), 1.3 + 0 * q0, -jnp.ones_like(q0),
    )  # fmt: skip
    s, x, v = (
        jnp.array([0.2, 0.7, 1.1]),
        jnp.array([-0.1, -1.5, 0.4]),
        jnp.array([0.3, 0.0, -0.6]),
    )

    @jax.jit
    def both(rel, s, x, v):
        compact = CompactMechanics(L_t, [tapes, *params])
        autodiff = AutodiffMechanics(L_c, list(consts))
        got, accels = compact.leg_ends(rel, s, x, v, _central_points)
        want, none = autodiff.leg_ends(rel, s, x, v, _central_points)
        central = lambda r, *p: autodiff.end_accels(r, _central_points(*p))
        return got, accels, want, none, jax.vmap(central)(rel, s, x, v, want[2])

    got, accels, want, none, central = both(rel, s, x, v)
    assert none is None
    jerk = np.asarray(want[3])
    assert not np.isfinite(jerk[1]) and np.all(np.isfinite(jerk[[0, 2]]))
    assert not np.isfinite(got[3][1])
    finite = lambda a: np.where(np.isfinite(a), a, 0.0)
    jax.tree.map(
        lambda a, b: np.testing.assert_allclose(finite(a), finite(b), rtol=1e-13),
        got, want
    )  # fmt: skip
    # (Both accelerations vanish there: a central jerk of zero.)
    np.testing.assert_allclose(accels[0][1], central[0][1], rtol=1e-13, atol=1e-300)
    np.testing.assert_allclose(accels[1][1], central[1][1], rtol=1e-13, atol=1e-300)


def test_a_pass_evaluates_the_point_tape_at_one_site(monkeypatch):
    # The release points and the legs' ends (and the central difference's points)
    # from one evaluation of the point tape in the program, with what the two
    # evaluations apart give, bit for bit.
    from lagrax._period import quantities as Q
    from lagrax._period.finish import _central_points
    from lagrax._period.units import lane_scales, lane_scales_from, release_point

    dtype = jnp.float64
    L_c, consts, L_t, tapes, params = _power_well_tapes(dtype)
    q0 = jnp.array([0.3, -0.5, jnp.nan], dtype)
    # Leg ends in lane units: the middle lane's at q = -1 (V'' infinite there).
    ends = (jnp.array([0.2, 0.7, 1.1]), jnp.array([-0.1, -1.0, 0.4]), jnp.zeros(3))

    def one_site(q0):
        mech = CompactMechanics(L_t, [tapes, *params])

        def run(out):
            at = out[:, 0]
            r = lane_scales_from(q0, at[Q.QDDOT], at[Q.MASS], at[Q.OK] != 0)
            return r, ends, jnp.sum(at)

        return mech.release_and_leg_ends(release_point(q0), run, _central_points)

    def apart(q0):
        mech = CompactMechanics(L_t, [tapes, *params])
        r = lane_scales(L_t, q0, [tapes, *params])
        return r, mech.leg_ends(r, *ends, _central_points)

    sites = []
    values = Q._values
    monkeypatch.setattr(Q, "_values", lambda *a: sites.append(1) or values(*a))
    jax.make_jaxpr(one_site)(q0)
    assert len(sites) == 1
    sites.clear()
    jax.make_jaxpr(apart)(q0)
    assert len(sites) >= 2  # (two sites; `vmap`'s rule traces one again)
    r, got_ends, _, legs = jax.jit(one_site)(q0)
    r_apart, legs_apart = jax.jit(apart)(q0)
    assert not np.isfinite(legs_apart[0][3][1])  # (three iterations: central points)
    same = lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    jax.tree.map(same, (r, legs), (r_apart, legs_apart))


def test_the_compact_far_turning_point_gives_what_autodiff_gives():
    # The compact tier finds the far turning point in one loop (one evaluation site
    # of the tape), the root's tangent by the implicit function (a custom JVP): the
    # asymmetric well V = k q²/2 + a q³/3, released at rest at q0 < 0, both in q0
    # and in k.
    from lagrax._period.far_turning_point import far_turning_point

    dtype = jnp.float64
    q0, q_m = jnp.array([-0.3, -0.8, jnp.nan], dtype), jnp.zeros(3, dtype)

    def roots(k, q0, compact):
        L_c, consts = canonical_lagrangian(asymmetric_well.lagrangian(k=k), dtype)
        if not compact:
            return far_turning_point(L_c, consts, q0, q_m)
        L_t, tapes = tier.tapes_of(L_c, consts, dtype)
        params = [jnp.asarray(c, dtype).reshape(()) for c in consts]
        params += [jnp.zeros((), dtype)] * (L_t.n_params - len(params))
        return far_turning_point(L_t, [tapes, *params], q0, q_m)

    want, got = roots(1.0, q0, False), roots(1.0, q0, True)
    assert np.all(np.asarray(want.found) == [True, True, False])
    np.testing.assert_array_equal(got.found, want.found)
    np.testing.assert_array_equal(got.in_range, want.in_range)
    np.testing.assert_allclose(got.q1[:2], want.q1[:2], rtol=1e-14)
    np.testing.assert_allclose(got.band[:2], want.band[:2], rtol=0.5)
    assert np.all(np.asarray(got.band[:2]) > 0)
    # dq1/dq0 = V'(q0)/V'(q1); dq1/dk = -(q1² - q0²)/2 / V'(q1).
    dV = lambda q: q + q**2
    q1 = np.asarray(want.q1[:2])
    for compact in (False, True):
        tangent = lambda k, q: jax.jvp(
            lambda k, q: roots(k, q, compact).q1, (k, q), (0.0 * k, jnp.ones(3))
        )[1]
        np.testing.assert_allclose(tangent(1.0, q0)[:2], dV(q0[:2]) / dV(q1), 1e-10)
        dk = jax.jvp(lambda k: roots(k, q0, compact).q1, (1.0,), (1.0,))[1]
        want_dk = -0.5 * (q1**2 - np.asarray(q0[:2]) ** 2) / dV(q1)
        np.testing.assert_allclose(dk[:2], want_dk, rtol=1e-10)


def test_the_tier_rule(monkeypatch, tmp_path):
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(tier, "_SPENT", collections.Counter())
    monkeypatch.setattr(tier, "_RATE", {})
    L_c, consts = canonical_lagrangian(pendulum.lagrangian(g=1.3), jnp.float64)
    taylor = TaylorStepper(order=20, max_step=np.inf)
    args = (L_c, consts, taylor, "config", 4096, jnp.float64)
    plan = tier.plan(*args)
    assert plan is not None and plan.stepper.order == 20
    assert plan.L.n_params % tier._PARAMS == 0
    # The time spent there with this L and configuration, and the work at hand,
    # against the specialized compile (a ski rental).
    assert not plan.repeated()
    tier._SPENT[(L_c, "config", "sweep")] = tier.COMPILE_S["sweep"] - 1e-3
    assert tier.plan(*args) is None
    # No rental while the specialized program compiles in another process.
    assert tier.plan(*args, waiting=True).repeated()
    assert tier.plan(L_c, consts, taylor, "other", 4096, jnp.float64) is not None
    tier._RATE["sweep"] = 1.0  # (a sweep this size would repay the compile)
    assert tier.plan(L_c, consts, taylor, "other", 4096, jnp.float64) is None
    monkeypatch.setenv("LAGRAX_COMPACT", "2")  # (always, where it applies)
    assert tier.plan(*args) is not None
    rk = sweep_module.stepper_of(dfx.Dopri8())
    assert tier.plan(L_c, consts, rk, "config", 8, jnp.float64) is None
    monkeypatch.setenv("LAGRAX_COMPACT", "0")
    assert tier.plan(*args) is None
    monkeypatch.setenv("LAGRAX_COMPACT", "1")
    monkeypatch.setenv("LAGRAX_CACHE_DIR", "")  # (nothing kept on disk: never)
    assert tier.plan(*args) is None


def test_the_compact_program_runs_once_at_hand_or_for_a_second_new_lagrangian(
    monkeypatch, tmp_path
):
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(tier, "_COMPILED", collections.Counter())
    monkeypatch.setattr(tier, "_NOTIFIED", set())
    monkeypatch.setattr(executables, "_LOADED", {})
    ran = []
    monkeypatch.setattr(executables, "call", lambda *a: ran.append(a) or a[3])
    taylor = TaylorStepper(order=20, max_step=np.inf)
    q0 = np.linspace(0.1, 1.0, 8)

    def compact_call(g):
        L_c, consts = canonical_lagrangian(pendulum.lagrangian(g=g), jnp.float64)
        plan = tier.plan(L_c, consts, taylor, "config", 8, jnp.float64)
        return tier.Compact(plan, "jitted", ("static",), None, (q0,))

    # The first new Lagrangian of a process: today's specialized program.
    assert compact_call(1.0).run("sweep", lambda: "specialized") == "specialized"
    assert not ran
    # The second: the compact program, compiled with a notice.
    with pytest.warns(UserWarning, match="once per machine"):
        assert compact_call(2.0).run("sweep", lambda: "specialized") is q0
    assert len(ran) == 1
    # At hand (compiled here, or on disk): taken at once, in a later process too.
    monkeypatch.setattr(tier, "_COMPILED", collections.Counter())
    call = compact_call(3.0)
    executables._LOADED[executables._key(call.static, call.args)] = None
    assert call.ready() and call.run("sweep", lambda: "specialized") is q0
    # A caller with several new Lagrangians (the command line): compact at once.
    executables._LOADED.clear()
    tier.several_lagrangians()
    assert compact_call(4.0).run("sweep", lambda: "specialized") is q0


def test_a_call_that_compiles_is_not_the_compact_programs_time(monkeypatch, tmp_path):
    # Else the first compact sweep, its compile included, would count as time spent
    # on the compact program, and the next one would compile the specialized program.
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    for name, empty in (("_COMPILED", collections.Counter()), ("_NOTIFIED", set())):
        monkeypatch.setattr(tier, name, empty)
    monkeypatch.setattr(tier, "_SPENT", collections.Counter())
    monkeypatch.setattr(tier, "_RATE", {})
    monkeypatch.setattr(executables, "_LOADED", {})
    monkeypatch.setattr(executables, "call", lambda *a: a[3])
    L_c, consts = canonical_lagrangian(pendulum.lagrangian(g=1.1), jnp.float64)
    taylor = TaylorStepper(order=20, max_step=np.inf)
    q0 = np.linspace(0.1, 1.0, 8)
    plan = tier.plan(L_c, consts, taylor, "config", 8, jnp.float64)
    call = tier.Compact(plan, "jitted", ("static",), None, (q0,))
    tier.several_lagrangians()
    with pytest.warns(UserWarning, match="once per machine"):
        call.run("sweep", lambda: "specialized")
    assert not tier._SPENT and not tier._RATE
    executables._LOADED[executables._key(call.static, call.args)] = None
    call.run("sweep", lambda: "specialized")
    assert sum(tier._SPENT.values()) > 0 and "sweep" in tier._RATE


@pytest.fixture
def compact_cache(executable_cache, monkeypatch):
    """The library's disk cache in a folder of the test's own, and `new_process()`
    emptying this process's tables of programs (also the compact ones)."""
    folder, loads, new_process = executable_cache

    def fresh():
        new_process()
        monkeypatch.setattr(executables, "_LOADED", {})

    fresh()
    return folder, loads, fresh


@pytest.mark.slow
def test_the_compact_tier_agrees_with_the_specialized_program(
    compact_cache, monkeypatch
):
    folder, loads, new_process = compact_cache
    q0 = np.concatenate([np.linspace(0.05, 3.14, 61), [np.nan, 3.5, 0.0]])
    runs = {}
    for mode in ("0", "2"):
        monkeypatch.setenv("LAGRAX_COMPACT", mode)
        runs[mode] = [
            lagrax.sweep_periods(pendulum.lagrangian(g=1.3), q0),
            lagrax.sweep_periods(asymmetric_well.lagrangian(), 0.3 * q0[:40]),
        ]
    for spec, comp in zip(runs["0"], runs["2"]):
        np.testing.assert_array_equal(spec.status, comp.status)
        np.testing.assert_allclose(comp.periods, spec.periods, rtol=2e-15)
        ok = np.asarray(spec.ok)
        ratio = (
            np.asarray(comp.error_estimate)[ok] / np.asarray(spec.error_estimate)[ok]
        )
        assert np.all((ratio > 0.5) & (ratio < 2.0))
    # Another Lagrangian of the class (and a rebuilt one): no compile, loaded by a
    # later process.
    compiled = executables.STATS["compiled"]
    res = lagrax.sweep_periods(pendulum.lagrangian(g=2.0), q0)
    assert executables.STATS["compiled"] == compiled
    new_process()
    again = lagrax.sweep_periods(pendulum.lagrangian(g=2.0), q0)
    assert executables.STATS["compiled"] == compiled and loads[-1]
    np.testing.assert_array_equal(again.periods, res.periods)
    # Its forward mode: the first derivative of a sweep, against the specialized one.
    mean = lambda q: lagrax.sweep_periods(pendulum.lagrangian(g=1.3), q).periods.mean()
    q = q0[:61]
    d_compact = jax.grad(mean)(q)
    monkeypatch.setenv("LAGRAX_COMPACT", "0")
    np.testing.assert_allclose(d_compact, jax.grad(mean)(q), rtol=1e-10, atol=1e-14)


@pytest.fixture
def later_tiers(monkeypatch, compact_cache):
    """The tiers as in a process of its own with an idle core, where a compile later
    is started (`executables.compile_later`): the disk cache's `loads`."""
    folder, loads, _ = compact_cache
    for name, empty in (("_COMPILED", collections.Counter()), ("_NOTIFIED", set())):
        monkeypatch.setattr(tier, name, empty)
    monkeypatch.setattr(tier, "_SPENT", collections.Counter())
    monkeypatch.setattr(tier, "_RATE", {})
    monkeypatch.setattr(executables, "_LATER", {})
    monkeypatch.setattr(executables, "_usable_cores", lambda: 2)
    monkeypatch.setenv("LAGRAX_BACKGROUND", "1")
    monkeypatch.setenv("LAGRAX_COMPACT", "1")
    return loads


@pytest.mark.slow
def test_a_repeated_sweep_takes_the_specialized_program_compiled_later(
    monkeypatch, later_tiers
):
    """Where a core is idle, a Lagrangian's second sweep on the compact tier (its
    executable at hand) starts its specialized program's compile in a worker
    process; once on disk, it takes over (same periods to rounding, same
    statuses)."""
    loads = later_tiers
    tier.several_lagrangians()
    q0 = jnp.linspace(0.1, 3.0, 64)
    L = pendulum.lagrangian(g=1.9)
    with pytest.warns(UserWarning, match="once per machine"):
        first = lagrax.sweep_periods(L, q0)
    lagrax.sweep_periods(L, q0)  # (the first that ran a compiled program)
    assert executables._LATER == {}
    lagrax.sweep_periods(L, q0)
    ((job),) = executables._LATER.values()
    job.thread.join(timeout=600)
    assert job.state == "done"
    ran = []
    monkeypatch.setattr(tier.Compact, "run", lambda *a: ran.append(a))
    third = lagrax.sweep_periods(L, q0)
    assert not ran and loads[-1] is True
    np.testing.assert_allclose(third.periods, first.periods, rtol=1e-14, atol=0)
    np.testing.assert_array_equal(third.status, first.status)


@pytest.mark.slow
def test_a_repeated_gradient_takes_the_specialized_program_compiled_later(
    monkeypatch, later_tiers
):
    """As for a sweep: a repeated `jax.grad` of a sweep (the forward jacobian's
    program) is taken over by its specialized program, compiled later."""
    loads = later_tiers
    tier.several_lagrangians("jacobian")
    q0 = jnp.linspace(0.1, 2.0, 32)

    def mean_period(g):
        L = lambda q, qd, t: 0.5 * qd[0] ** 2 + g * jnp.cos(q[0])
        return jnp.mean(lagrax.sweep_periods(L, q0).periods)

    grad = jax.grad(mean_period)
    with pytest.warns(UserWarning, match="once per machine"):
        first = grad(1.3)
    grad(1.3)  # (the first that ran a compiled program)
    assert executables._LATER == {}
    grad(1.3)
    ((job),) = executables._LATER.values()
    job.thread.join(timeout=600)
    assert job.state == "done"
    ran = []
    monkeypatch.setattr(tier.Compact, "run", lambda *a: ran.append(a))
    third = grad(1.3)
    assert not ran and loads[-1] is True
    np.testing.assert_allclose(third, first, rtol=1e-12)
    # d/dg of the mean period of g: -T/(2g) for each amplitude.
    exact = -np.mean(pendulum.period(np.asarray(q0), g=1.3)) / (2 * 1.3)
    np.testing.assert_allclose(third, exact, rtol=1e-10)
