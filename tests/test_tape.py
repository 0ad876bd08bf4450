"""Taylor coefficients from a tape (`lagrax._taylor.tape`) against the specialized
recurrences, and the tape path of the period sweep against the specialized one."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax._cache import executables
from lagrax._jaxpr.canonical import canonical_lagrangian
from lagrax._period import tier
from lagrax._period.mechanics import AutodiffMechanics
from lagrax._taylor.program import taylor_coefficients
from lagrax._taylor.tape import build_tape, tape_coefficients, tape_series
from lagrax.systems import asymmetric_well, pendulum


f64 = np.float64
K = 12


def _many_opcodes(s, x, v, p):
    """An acceleration through most opcodes (values kept in their domains)."""
    u = 0.3 + 0.2 * jnp.sin(x) + 0.1 * v
    w = jnp.exp(0.5 * x) + jnp.log1p(u) + jnp.sqrt(1.0 + u * u) + u**1.5
    w = w + jnp.tanh(v) - jnp.arctan(x * p) + jax.nn.sigmoid(u) / jnp.cosh(x)
    w = w + jnp.where(x > 0, jnp.expm1(x), jnp.sinh(x)) + jnp.tan(0.3 * u)
    w = w + jnp.maximum(x, 0.05) - jnp.abs(v) + jnp.log(u) / (2.0 + x**2)
    return -w * p + s


def _compare(accel, n_params, lanes):
    s, x, v, *params = lanes
    ref = taylor_coefficients(lambda s, x, v, p: accel(s, x, v, *p), K, f64)(
        s, x, v, tuple(params)
    )
    tape = build_tape(accel, 3 + n_params, f64)
    got = jax.jit(lambda t, *a: tape_coefficients(t, K, *a[:3], a[3:]))(
        tape, s, x, v, *params
    )
    for r, g in zip(ref, got):
        r, g = np.asarray(r), np.asarray(g)
        # Each order against the size of that order's coefficients.
        scale = np.max(np.abs(r), axis=1, keepdims=True) + 1e-300
        assert np.max(np.abs(g - r) / scale) < 1e-12


def test_pendulum_and_well_coefficients():
    rng = np.random.default_rng(0)
    W = 6
    lanes = [np.zeros(W), rng.uniform(-0.5, 0.5, W), rng.uniform(-0.5, 0.5, W)]
    for L in (pendulum.lagrangian(g=1.7), asymmetric_well.lagrangian()):
        L_c, consts = canonical_lagrangian(L, f64)
        accel_one = AutodiffMechanics(L_c, consts).scaled_acceleration()
        q0 = rng.uniform(0.2, 0.9, W)
        accel = lambda s, x, v, q0, Qs, tau: accel_one(q0, Qs, tau, s, x, v)
        _compare(accel, 3, lanes + [q0, np.abs(q0), np.full(W, 0.8)])


def test_many_opcodes_coefficients():
    rng = np.random.default_rng(1)
    W = 5
    lanes = [
        rng.uniform(-1, 1, W),
        rng.uniform(-0.4, 0.4, W),
        rng.uniform(-0.4, 0.4, W),
        rng.uniform(0.5, 2.0, W),
    ]
    _compare(_many_opcodes, 1, lanes)


def test_series_at_order_one_is_value_and_derivative():
    f = lambda q, p: jnp.cos(q) * p + q**3 / (1.0 + q * q)
    tape = build_tape(f, 2, f64, series=(0,))
    q = np.linspace(-1.0, 1.0, 7)
    p = np.full(7, 2.5)
    out = tape_series(tape, [np.stack([q, np.ones(7)]), p], 1)
    value, slope = jax.vmap(jax.value_and_grad(f))(q, p)
    np.testing.assert_allclose(out[0, 0], value, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(out[0, 1], slope, rtol=1e-14, atol=1e-15)


def test_programs_of_arrays_are_not_taped():
    with pytest.raises(NotImplementedError):
        build_tape(lambda s, x, v: jnp.sum(jnp.stack([x, v]) ** 2), 3, f64)


@pytest.mark.slow
def test_tape_path_agrees_with_the_specialized_sweep(
    monkeypatch, tmp_path, without_jax_cache
):
    from lagrax._period import sweep as sweep_module

    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(tier, "_SWEPT", tier.collections.Counter())
    monkeypatch.setattr(executables, "_LOADED", {})
    # (The tape path's entries: the specialized sweeps' are `p*.bin`.)
    stored = lambda: sorted(tmp_path.glob("t*.bin"))
    q0 = jnp.linspace(0.05, 3.0, 96)
    q1 = jnp.linspace(0.1, 0.9, 40)
    well = asymmetric_well.lagrangian()
    monkeypatch.delenv("LAGRAX_TAPE_TIER", raising=False)
    refs = [
        lagrax.sweep_periods(pendulum.lagrangian(), q0),
        lagrax.sweep_periods(well, q1, solver=lagrax.Taylor()),
    ]
    assert stored() == [] and executables._LOADED == {}  # (off by default)
    monkeypatch.setenv("LAGRAX_TAPE_TIER", "1")
    taped = lagrax.sweep_periods(pendulum.lagrangian(), q0)
    assert len(stored()) == 1  # the executable, on disk
    # Another Lagrangian of the same sizes and another number of amplitudes: the
    # same executable, from disk (as in a new process: the table of loaded
    # programs emptied).
    monkeypatch.setattr(executables, "_LOADED", {})
    other = lagrax.sweep_periods(well, q1, solver=lagrax.Taylor())
    assert len(stored()) == 1 and len(executables._LOADED) == 1
    for res, ref in zip((taped, other), refs):
        np.testing.assert_array_equal(res.status, ref.status)
        np.testing.assert_allclose(res.periods, ref.periods, rtol=1e-13)
        np.testing.assert_allclose(res.error_estimate, ref.error_estimate, rtol=0.2)
    # Beyond its share of amplitudes, the specialized program (compiled above).
    monkeypatch.setattr(tier, "SPECIALIZE_AFTER", 0)
    hits = sweep_module._sweep_jit.cache_info().hits
    lagrax.sweep_periods(pendulum.lagrangian(), q0)
    assert sweep_module._sweep_jit.cache_info().hits == hits + 1


def test_tape_tier_switch(monkeypatch):
    monkeypatch.setattr(tier, "_SWEPT", tier.collections.Counter())
    L_c, consts = canonical_lagrangian(pendulum.lagrangian(), f64)
    args = (L_c, consts, lagrax.Taylor(), "config", jnp.linspace(0.1, 1.0, 8), 8)
    for value in ("0", " "):
        monkeypatch.setenv("LAGRAX_TAPE_TIER", value)
        assert tier.choose(*args) is None
    monkeypatch.setenv("LAGRAX_TAPE_TIER", "1")
    assert tier.choose(*args) is not None and tier._SWEPT[(L_c, "config")] == 8
    monkeypatch.setenv("LAGRAX_TAPE_TIER", "yes")
    with pytest.raises(ValueError, match="LAGRAX_TAPE_TIER must be 0 or 1"):
        lagrax.sweep_periods(pendulum.lagrangian(), jnp.linspace(0.1, 1.0, 8))
