"""`lagrax.Taylor` as a diffrax solver: plain vector fields, dense output, events,
batching, derivatives, time reversal, and Lagrangians through `simulate`."""

from functools import partial

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import lagrax


K = 6  # a low order keeps compile times small; the method is the same at any K


def oscillator(t, y, args):
    # x'' = -w^2 x as a dict state: any pytree, no lagrax mechanics.
    w = args["w"]
    return {"x": y["v"], "v": -(w**2) * y["x"]}


def solve(y0, t1, *, args=None, solver=None, dt0=None, **kw):
    kw.setdefault("stepsize_controller", dfx.PIDController(rtol=1e-12, atol=1e-12))
    return dfx.diffeqsolve(
        dfx.ODETerm(oscillator),
        solver or lagrax.Taylor(order=K),
        0.0,
        t1,
        dt0,
        y0,
        args=args or {"w": jnp.asarray(2.0)},
        **kw,
    )


def test_plain_vector_field_pytree_state_and_dense_output():
    # Exact: x = cos(2t), v = -2 sin(2t); dense output read from the polynomials.
    ts = jnp.linspace(0.0, 5.0, 23)
    y0 = {"x": jnp.asarray(1.0), "v": jnp.asarray(0.0)}
    sol = solve(y0, 5.0, saveat=dfx.SaveAt(ts=ts, dense=True))
    assert sol.result == dfx.RESULTS.successful
    np.testing.assert_allclose(sol.ys["x"], jnp.cos(2 * ts), atol=1e-10)
    np.testing.assert_allclose(sol.ys["v"], -2 * jnp.sin(2 * ts), atol=2e-10)
    # Between steps and save points: the step's polynomial.
    tt = jnp.linspace(0.0, 5.0, 97)
    dense = jax.vmap(sol.evaluate)(tt)["x"]
    np.testing.assert_allclose(dense, jnp.cos(2 * tt), atol=1e-10)


def test_event_located_on_the_polynomial():
    # First zero of x = cos(2t): t = pi/4.
    event = dfx.Event(
        lambda t, y, args, **kw: y["x"], root_finder=optx.Newton(1e-13, 1e-13)
    )
    y0 = {"x": jnp.asarray(1.0), "v": jnp.asarray(0.0)}
    sol = solve(y0, 10.0, event=event)
    assert sol.result == dfx.RESULTS.event_occurred
    np.testing.assert_allclose(sol.ts[-1], np.pi / 4, atol=1e-11)


def test_vmap_lanes_match_single_solves_and_backward_time():
    ws = jnp.array([0.5, 1.0, 3.0])

    def final(w, t1):
        y0 = {"x": jnp.asarray(1.0), "v": jnp.asarray(0.0)}
        return solve(y0, t1, args={"w": w}).ys["x"][-1]

    out = jax.jit(jax.vmap(final, (0, None)))(ws, 3.0)
    for w, x in zip(ws, out):
        assert float(x) == pytest.approx(float(final(w, 3.0)), abs=1e-13)
        assert float(x) == pytest.approx(np.cos(3.0 * float(w)), abs=1e-10)
    # t1 < t0: diffrax reverses time around the solver; cos is even.
    assert float(final(ws[1], -3.0)) == pytest.approx(np.cos(3.0), abs=1e-10)


def _final_x(x0, w, adjoint):
    # x(t) = x0 cos(wt) + v0 sin(wt)/w: dx/dx0 = cos(wt), dx/dw = -x0 t sin(wt).
    y0 = {"x": x0, "v": jnp.zeros_like(x0)}
    ctrl = dfx.PIDController(rtol=1e-10, atol=1e-10)
    sol = solve(y0, 2.0, args={"w": w}, adjoint=adjoint, stepsize_controller=ctrl)
    return sol.ys["x"][-1]


def test_forward_mode_derivatives():
    x0, w = jnp.asarray(0.7), jnp.asarray(1.5)
    fwd = jax.jacfwd(_final_x, argnums=(0, 1))(x0, w, dfx.ForwardMode())
    np.testing.assert_allclose(fwd[0], np.cos(3.0), atol=1e-8)
    np.testing.assert_allclose(fwd[1], -0.7 * 2.0 * np.sin(3.0), atol=1e-7)


@pytest.mark.slow
def test_reverse_mode_derivatives():
    x0, w = jnp.asarray(0.7), jnp.asarray(1.5)
    rev = jax.grad(_final_x, argnums=(0, 1))(x0, w, dfx.RecursiveCheckpointAdjoint())
    np.testing.assert_allclose(rev[0], np.cos(3.0), atol=1e-8)
    np.testing.assert_allclose(rev[1], -0.7 * 2.0 * np.sin(3.0), atol=1e-7)


def test_reverse_mode_through_powers_matches_forward_mode():
    # x' = -x^3 - x^2: powers become products of series in the recurrences, which
    # `jax.grad` transposes (with the parameters JAX's rules require).
    def final(x0, adjoint=dfx.RecursiveCheckpointAdjoint()):
        term = dfx.ODETerm(lambda t, x, args: -(x**3) - jnp.square(x))
        sol = dfx.diffeqsolve(
            term, lagrax.Taylor(order=4), 0.0, 0.5, 0.1, x0,
            stepsize_controller=dfx.ConstantStepSize(), adjoint=adjoint,
        )  # fmt: skip
        return sol.ys[-1]

    x0 = jnp.asarray(0.6)
    rev = jax.grad(final)(x0)
    fwd = jax.jacfwd(final)(x0, dfx.ForwardMode())
    # (forward mode is checked against closed forms above)
    np.testing.assert_allclose(rev, fwd, rtol=1e-13)
    assert float(rev) != 0.0


def test_convergence_order_fixed_steps():
    # Local error h^(K+1): the global error at order 4 falls as h^4.
    errs = []
    dts = [0.2, 0.1, 0.05]
    for dt in dts:
        y0 = {"x": jnp.asarray(1.0), "v": jnp.asarray(0.0)}
        sol = solve(
            y0,
            2.0,
            solver=lagrax.Taylor(order=4),
            stepsize_controller=dfx.ConstantStepSize(),
            dt0=dt,
        )
        errs.append(abs(float(sol.ys["x"][-1]) - np.cos(4.0)))
    slope = np.polyfit(np.log(dts), np.log(errs), 1)[0]
    assert 3.7 < slope < 4.3


# Taylor() on two coordinates runs every time in the three-coordinate test below.
@pytest.mark.slow
def test_simulate_double_pendulum_against_dopri8():
    # Lagrange's equations of a closed-form double pendulum, released from rest.
    def L(q, qdot, t):
        T = qdot[0] ** 2 + 0.5 * qdot[1] ** 2 + qdot[0] * qdot[1] * jnp.cos(q[0] - q[1])
        return T + 2 * 9.81 * jnp.cos(q[0]) + 9.81 * jnp.cos(q[1])

    q0, v0 = jnp.array([0.8, -0.4]), jnp.zeros(2)
    ts = jnp.linspace(0.0, 2.0, 5)
    kw = dict(saveat=dfx.SaveAt(ts=ts))
    ref = lagrax.simulate(
        L, q0, v0, 0.0, 2.0, solver=dfx.Dopri8(), rtol=1e-13, atol=1e-13, **kw
    )
    sol = lagrax.simulate(
        L, q0, v0, 0.0, 2.0, solver=lagrax.Taylor(order=K), rtol=1e-11, atol=1e-11, **kw
    )
    np.testing.assert_allclose(sol.ys[0], ref.ys[0], atol=1e-9)
    np.testing.assert_allclose(sol.ys[1], ref.ys[1], atol=1e-8)


def test_non_ode_term_rejected():
    term = dfx.ControlTerm(lambda t, y, args: y, dfx.LinearInterpolation(
        ts=jnp.array([0.0, 1.0]), ys=jnp.array([0.0, 1.0])
    ))  # fmt: skip
    with pytest.raises(TypeError, match="ODETerm"):
        dfx.diffeqsolve(term, lagrax.Taylor(order=K), 0.0, 1.0, 0.1, jnp.asarray(1.0))


def _check_series_against_jvps(field, q0, v0, order=4):
    """The series of y' = F(y) from the system's program against nested JVPs,
    y_k = y^(k)(0) / k!, up to `order`; returns the program."""
    from lagrax._taylor.system import System

    n = q0.shape[0]

    def F(y):
        return jnp.concatenate(field(0.0, (y[:n], y[n:]), None))

    system = System(lambda t, ys, p: list(field(t, tuple(ys), None)), 0.0, [q0, v0], [])
    coefs = jax.jit(lambda q, v: system.coefficients(order, jnp.zeros(1), [q, v], []))(
        q0[None], v0[None]
    )
    series = np.array([[float(c[k][0]) for c in coefs] for k in range(order + 1)])

    def derivatives(y):
        g, out = F, []
        for _ in range(order):
            out.append(g(y))
            g = (lambda g: lambda y: jax.jvp(g, (y,), (F(y),))[1])(g)
        return out

    y = jnp.concatenate([q0, v0])
    factorial = 1.0
    for k, d in enumerate(jax.jit(derivatives)(y), start=1):
        factorial *= k
        np.testing.assert_allclose(series[k], d / factorial, rtol=1e-12, atol=1e-12)
    return system.prog


# The solve recurrence of n = 3 every time in test_merged_program_of_a_particle_chain
# (a chain of three links: its series against JVPs, its one "solve" node).
@pytest.mark.slow
def test_mass_matrix_solve_recurrence_three_coordinates():
    # n = 3 takes the marked solve (one factorization of M_0 per step).
    def L(q, qdot, t):
        s = jnp.sin(q)
        T = 0.5 * qdot @ qdot + 0.05 * (s @ qdot) ** 2  # M = I + 0.1 s s^T
        return T - 0.5 * q @ q - 0.1 * q[0] * q[1] * q[2]

    q0, v0 = jnp.array([0.4, -0.3, 0.7]), jnp.array([0.2, 0.5, -0.1])
    prog = _check_series_against_jvps(lagrax.vector_field(L), q0, v0)
    assert any(node.kind == "solve" for node in prog.nodes)


def test_merged_program_of_a_particle_chain():
    # A chain written from particle positions: its autodiff equations repeat
    # products up to operand order and negate twice; the program merges them and
    # reads the mass matrix's upper triangle only, with the same series.
    def positions(q, t):
        return jnp.stack([jnp.cumsum(jnp.sin(q)), -jnp.cumsum(jnp.cos(q))], axis=1)

    L = lagrax.particle_lagrangian(
        jnp.ones(3), positions, lambda r, t: 9.81 * jnp.sum(r[:, 1])
    )
    q0, v0 = jnp.array([0.4, -0.3, 0.2]), jnp.array([0.1, 0.5, -0.2])
    prog = _check_series_against_jvps(lagrax.vector_field(L), q0, v0)
    seen = set()
    for node in prog.nodes:
        if node.kind in ("add", "add_any", "mul"):
            key = (node.kind, frozenset(node.ins))
            assert key not in seen
            seen.add(key)
        if node.kind == "neg":
            assert all(m.kind != "neg" or m.outs[0] not in node.ins for m in prog.nodes)
    (solve,) = [node for node in prog.nodes if node.kind == "solve"]
    M = np.array(solve.ins[:9]).reshape(3, 3)
    np.testing.assert_array_equal(M, M.T)


def _double_pendulum(q, qdot, t):
    T = qdot[0] ** 2 + 0.5 * qdot[1] ** 2 + qdot[0] * qdot[1] * jnp.cos(q[0] - q[1])
    return T + 2 * 9.81 * jnp.cos(q[0]) + 9.81 * jnp.cos(q[1])


def _end(q0, adjoint=dfx.RecursiveCheckpointAdjoint()):
    sol = lagrax.simulate(
        _double_pendulum, q0, jnp.zeros(2), 0.0, 0.4, solver=lagrax.Taylor(),
        rtol=1e-12, atol=1e-12, adjoint=adjoint,
    )  # fmt: skip
    return sol.ys[0][-1]


def test_compact_program_under_vmap(monkeypatch):
    """A large enough step program takes the compact program (the double pendulum at
    order 20), whose lanes a caller's `vmap` extends: the same states as single
    solves."""
    import lagrax._taylor.diffrax_solver as solver_module

    used = []
    real = solver_module._compact_tape
    monkeypatch.setattr(
        solver_module, "_compact_tape", lambda *a: used.append(1) or real(*a)
    )
    q0 = jnp.array([[0.5, -0.3], [0.2, 0.6]])
    batched = jax.jit(jax.vmap(_end))(q0)
    assert used
    single = np.stack([np.asarray(_end(q)) for q in q0])
    np.testing.assert_allclose(batched, single, rtol=0, atol=1e-13)


@pytest.mark.slow
def test_compact_program_derivatives():
    """Forward and reverse mode (`RecursiveCheckpointAdjoint`) through the compact
    program match central differences."""
    q0 = jnp.array([0.5, -0.3])
    fwd = jax.jacfwd(lambda q: _end(q, dfx.ForwardMode()))(q0)
    rev = jax.jacrev(_end)(q0)
    eps = 1e-6
    fd = np.stack(
        [
            (np.asarray(_end(q0 + eps * e)) - np.asarray(_end(q0 - eps * e)))
            / (2 * eps)
            for e in np.eye(2)
        ],
        axis=1,
    )
    np.testing.assert_allclose(fwd, fd, atol=1e-7)
    np.testing.assert_allclose(rev, fwd, rtol=0, atol=1e-11)


def test_inline_program_equals_the_size_class_program(monkeypatch):
    """The program compiled inside a caller's `jit` (`inline_coefficients`: blocks
    unrolled into runs, each inner sum over the rows that weigh it) against the
    size-class program, on a tape with constant and per-lane linear nodes and
    Cauchy nodes of every sum (plain, weighted, both), its lanes in passes (the
    last one padded)."""
    from lagrax._jaxpr.canonical import canonical_lagrangian
    from lagrax._taylor import compact
    from lagrax._trajectory.batch import _system

    def L(q, qdot, t):
        T = 0.5 * qdot @ qdot + 0.25 * jnp.cos(q[0] - q[1]) * qdot[0] * qdot[1]
        V = (2 + q[0] ** 2) ** 1.5 + jnp.abs(q[1]) * q[1] ** 2 - jnp.exp(0.3 * q[1])
        return T - V

    L_c, consts = canonical_lagrangian(L, jnp.float64, 2)
    prog = _system(L_c, consts, None, jnp.zeros(2), jnp.zeros(2)).prog
    tape = compact.build(prog, prog.inputs, prog.params, prog.outs, jnp.float64)
    seq = np.asarray(tape.seq1)[: int(tape.blocks[1])]
    assert set(seq[:, 0]) == {0, 1, 2, 3, 4}  # (sums plain, weighted, both; linear)
    rng = np.random.default_rng(0)
    t, ys = jnp.asarray(rng.uniform(0, 1, 3)), jnp.asarray(rng.uniform(-1, 1, (4, 3)))
    args = (t, list(ys), [jnp.ones(3)])
    K = 9
    want = np.asarray(jax.jit(partial(compact.compact_coefficients, tape, K))(*args))
    scale = np.max(np.abs(want), axis=(0, 2), keepdims=True)
    monkeypatch.setattr(compact, "_LANES", 2)
    got = np.asarray(jax.jit(compact.lane_function(tape, K, inline=True))(*args))
    np.testing.assert_allclose(got / scale, want / scale, rtol=0, atol=1e-14)
