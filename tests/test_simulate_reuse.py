"""An eager `lagrax.simulate` is compiled per body of `L`: a rebuilt `L` with new
parameter values reuses the program (in this process, and from the library's disk
cache in a later one, found without lowering) and gives the numbers of its own
values; another body, or a force, compiles a program of its own."""

import collections

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax._cache import executables
from lagrax.systems import pendulum

from .helpers import counting_compiles


Q0, V0 = jnp.array([1.0]), jnp.array([0.0])
TS = jnp.linspace(0.0, 1.0, 5)
TOL = dict(rtol=1e-10, atol=1e-10)


@pytest.fixture
def compiles():
    """The number of XLA compiles since the last call of the returned function."""
    with counting_compiles() as count:
        seen = [0]

        def since():
            now, seen[0] = count() - seen[0], count()
            return now

        yield since


def _pendulum(g, t1=1.0, **kwargs):
    """The pendulum (m = r = 1) from rest at q = 1, saved at `TS * t1`."""
    return lagrax.simulate(
        pendulum.lagrangian(g=g), Q0, V0, 0.0, t1,
        saveat=dfx.SaveAt(ts=TS * t1), **TOL | kwargs,
    )  # fmt: skip


def test_a_rebuilt_lagrangian_reuses_the_program(compiles):
    _pendulum(1.0, t1=2.0)
    compiles()
    rebuilt = _pendulum(4.0)
    assert compiles() == 0
    # From rest, q(t; g) = q(t sqrt(g); 1): g = 4 over [0, 1] is g = 1 over [0, 2].
    slow = _pendulum(1.0, t1=2.0)
    np.testing.assert_allclose(rebuilt.ys[0], slow.ys[0], rtol=0, atol=1e-8)
    assert not np.allclose(rebuilt.ys[0], _pendulum(1.0).ys[0])
    assert isinstance(rebuilt.result, type(dfx.RESULTS.successful))
    assert rebuilt.stats["max_steps"] == 16384


def test_a_rebuilt_lagrangian_matches_a_plain_diffrax_solve():
    L = pendulum.lagrangian(g=2.5)
    sol = lagrax.simulate(L, Q0, V0, 0.0, 1.0, saveat=dfx.SaveAt(ts=TS), **TOL)
    controller = dfx.PIDController(**TOL)
    plain = dfx.diffeqsolve(
        dfx.ODETerm(lagrax.vector_field(L)), dfx.Tsit5(), 0.0, 1.0, None, (Q0, V0),
        saveat=dfx.SaveAt(ts=TS), stepsize_controller=controller,
    )  # fmt: skip
    np.testing.assert_allclose(sol.ys[0], plain.ys[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.ys[1], plain.ys[1], rtol=0, atol=1e-12)


def test_another_body_compiles_its_own_program(compiles):
    _pendulum(1.0)
    compiles()
    spring = lambda q, qdot, t: 0.5 * qdot[0] ** 2 - 0.5 * q[0] ** 2
    sol = lagrax.simulate(spring, Q0, V0, 0.0, 1.0, saveat=dfx.SaveAt(ts=TS), **TOL)
    assert compiles() > 0
    np.testing.assert_allclose(sol.ys[0][:, 0], np.cos(TS), rtol=0, atol=1e-8)


def _damped(zeta, saveat=dfx.SaveAt(ts=TS)):
    """The damped oscillator q'' = -q - 2 zeta q' from rest at q = 1, by a force,
    saved at `TS` (or as `saveat` says)."""
    spring = lambda q, qdot, t: 0.5 * qdot[0] ** 2 - 0.5 * q[0] ** 2
    force = lambda q, qdot, t: -2.0 * zeta * qdot
    sol = lagrax.simulate(spring, Q0, V0, 0.0, 1.0, force=force, saveat=saveat, **TOL)
    t = np.asarray(sol.ts)
    w = np.sqrt(1 - zeta**2)
    exact = np.exp(-zeta * t) * (np.cos(w * t) + zeta / w * np.sin(w * t))
    return sol.ys[0][:, 0], exact


def test_a_force_gives_its_own_numbers():
    # (Each force is a new function: its values are in its program, never reused
    # for another.)
    for zeta in (0.1, 0.4):
        q, exact = _damped(zeta)
        np.testing.assert_allclose(q, exact, rtol=0, atol=1e-8)


@pytest.fixture
def cache(executable_cache, monkeypatch):
    """`executable_cache`, with the programs `cached_call` lowers recorded."""
    folder, loads, new_process = executable_cache
    lowerings = []
    program_key = executables._program_key

    def lowered(lowered, options):
        lowerings.append(lowered)
        return program_key(lowered, options)

    monkeypatch.setattr(executables, "_program_key", lowered)
    return folder, loads, new_process, lowerings


def test_a_later_process_loads_the_program_of_a_rebuilt_lagrangian(cache):
    folder, loads, new_process, lowerings = cache
    first = lagrax.simulate(pendulum.lagrangian(g=1.0), Q0, V0, 0.0, 2.0, **TOL)
    # The solve and the check of its start, each compiled once and written.
    assert loads == [False, False] and len(lowerings) == 2
    assert len(list(folder.glob("p*.bin"))) == 2
    new_process()
    lowerings.clear()
    again = lagrax.simulate(pendulum.lagrangian(g=4.0), Q0, V0, 0.0, 1.0, **TOL)
    assert loads[2:] == [True, True] and lowerings == []
    np.testing.assert_allclose(again.ys[0], first.ys[0], rtol=0, atol=1e-8)
    assert again.ts[-1] == 1.0 and first.ts[-1] == 2.0


def test_a_later_process_with_a_force_finds_the_program_by_lowering(cache):
    folder, loads, new_process, lowerings = cache
    q, exact = _damped(0.2, dfx.SaveAt(t1=True))
    new_process()
    lowerings.clear()
    q_again, _ = _damped(0.2, dfx.SaveAt(t1=True))
    # (A function has no text for a pre-key: found by its lowered program.)
    assert loads[-2:] == [True, True] and len(lowerings) == 2
    np.testing.assert_array_equal(q_again, q)
    np.testing.assert_allclose(q, exact, rtol=0, atol=1e-8)


@pytest.mark.parametrize(
    "how", [dict(saveat=dfx.SaveAt(ts=TS * 2.0)), dict(dt0=0.01)], ids=["ts", "dt0"]
)
def test_a_program_with_save_times_or_dt0_is_kept_in_this_process(cache, how):
    # (diffrax checks save times and dt0 by a callback in its program: such a
    # program cannot be written to disk, so a later process compiles it again.)
    folder, loads, new_process, lowerings = cache
    run = lambda: lagrax.simulate(pendulum.lagrangian(), Q0, V0, 0.0, 2.0, **TOL, **how)
    first = run()
    assert loads == [False, False] and len(list(folder.glob("p*.bin"))) == 1
    rebuilt = run()
    assert len(loads) == 2  # (this process's programs: nothing looked for on disk)
    new_process()
    again = run()
    assert loads[2:] == [True, False]  # (the start's program loaded; the solve's not)
    for sol in (rebuilt, again):
        np.testing.assert_array_equal(sol.ys[0], first.ys[0])
        np.testing.assert_array_equal(sol.ts, first.ts)
    if "saveat" in how:
        np.testing.assert_array_equal(again.ts, TS * 2.0)


@pytest.mark.parametrize("t1", [2.0, -2.0], ids=["forward", "backward"])
def test_a_fixed_step_solve_is_loaded_by_a_later_process(cache, t1):
    # (Its step goes to diffrax in the controller, which diffrax does not check by a
    # callback: the program is written to disk.)
    folder, loads, new_process, lowerings = cache
    dt0 = 0.1 * np.sign(t1)
    run = lambda g: lagrax.simulate(
        pendulum.lagrangian(g=g), Q0, V0, 0.0, t1, solver=dfx.Euler(), dt0=dt0
    )
    first = run(1.0)
    assert loads == [False, False] and len(list(folder.glob("p*.bin"))) == 2
    new_process()
    lowerings.clear()
    again = run(1.0)
    assert loads[2:] == [True, True] and lowerings == []
    np.testing.assert_array_equal(again.ys[0], first.ys[0])
    # The steps diffrax takes with `ConstantStepSize()` and this `dt0`, bit for bit.
    plain = dfx.diffeqsolve(
        dfx.ODETerm(lagrax.vector_field(pendulum.lagrangian(g=1.0))), dfx.Euler(),
        0.0, t1, dt0, (Q0, V0),
    )  # fmt: skip
    np.testing.assert_array_equal(first.ys[0], plain.ys[0])
    assert first.stats["num_steps"] == plain.stats["num_steps"] == 20


def test_a_failed_solve_loaded_from_disk_still_raises(cache):
    folder, loads, new_process, lowerings = cache
    many = dict(max_steps=4, **TOL)
    sol = lagrax.simulate(pendulum.lagrangian(), Q0, V0, 0.0, 10.0, throw=False, **many)
    assert sol.result == dfx.RESULTS.max_steps_reached
    new_process()
    with pytest.raises(RuntimeError, match="maximum number of solver steps"):
        lagrax.simulate(pendulum.lagrangian(), Q0, V0, 0.0, 10.0, **many)
    assert loads[-2:] == [True, True]


@pytest.mark.parametrize(
    "t1, ts, match",
    [
        (1.0, [0.0, 0.5, 0.25], r"`saveat.ts` must run from t0 to t1 \(increasing"),
        (-1.0, [0.0, 0.5], r"`saveat.ts` must run from t0 to t1 \(decreasing"),
        (1.0, [0.0, 0.5, 1.5], r"`saveat.ts` must lie between t0=0.0 and t1=1.0"),
        (1.0, [0.0, np.nan], r"`saveat.ts` must be finite"),
        (1.0, [[0.0, 0.5]], r"`saveat.ts` must be a 1-D array"),
    ],
    ids=["unsorted", "backwards", "outside", "nan", "2-d"],
)
def test_bad_save_times_are_named(t1, ts, match):
    saveat = dfx.SaveAt(ts=jnp.asarray(ts))
    with pytest.raises(ValueError, match=match):
        lagrax.simulate(pendulum.lagrangian(), Q0, V0, 0.0, t1, saveat=saveat)


def test_save_times_backwards_in_time_are_accepted():
    # (From t0 = 0 back to t1 = -1, as diffrax asks: decreasing, within [t1, t0].)
    ts = -TS
    sol = lagrax.simulate(
        pendulum.lagrangian(), Q0, V0, 0.0, -1.0, saveat=dfx.SaveAt(ts=ts), **TOL
    )
    ahead = _pendulum(1.0)  # (from rest: q(-t) = q(t))
    np.testing.assert_allclose(sol.ys[0], ahead.ys[0], rtol=0, atol=1e-8)


def test_a_dt0_of_the_wrong_sign_is_named():
    with pytest.raises(ValueError, match="`dt0` must have the sign of t1 - t0"):
        lagrax.simulate(pendulum.lagrangian(), Q0, V0, 0.0, -1.0, dt0=0.1)


def test_under_jit_and_vmap_it_is_traced_in_place(monkeypatch):
    monkeypatch.setattr(executables, "_PROGRAMS", collections.OrderedDict())
    run = lambda g, q: lagrax.simulate(
        lambda q, qdot, t: 0.5 * qdot[0] ** 2 + g * jnp.cos(q[0]), q, V0, 0.0, 1.0,
        **TOL,
    ).ys[0][-1, 0]  # fmt: skip
    out = jax.jit(jax.vmap(run))(jnp.array([1.0, 4.0]), jnp.array([[0.5], [0.5]]))
    assert len(executables._PROGRAMS) == 0
    # g = 4 over [0, 1] is g = 1 over [0, 2].
    slow = lagrax.simulate(pendulum.lagrangian(), jnp.array([0.5]), V0, 0.0, 2.0, **TOL)
    np.testing.assert_allclose(out[1], slow.ys[0][-1, 0], rtol=0, atol=1e-8)


# (Reverse mode through a simulate every time in tests/test_taylor_diffrax.py; an L
# closing over a tracer, traced in place, in
# test_under_jit_and_vmap_it_is_traced_in_place.)
@pytest.mark.slow  # reverse mode through the solve: its compilation is the cost
def test_a_lagrangian_closing_over_a_tracer_is_differentiated(cache):
    # (Concrete state and times, and L closes over the tracer of `jax.grad`: run as
    # diffrax's, never through a cached executable.)
    q_end = lambda g: _pendulum(g).ys[0][-1, 0]
    h = 1e-4
    central = (q_end(2.0 + h) - q_end(2.0 - h)) / (2 * h)
    np.testing.assert_allclose(jax.grad(q_end)(2.0), central, rtol=1e-6)
