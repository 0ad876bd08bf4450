import os
import subprocess
import sys
import textwrap

import pytest


SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    import lagrax
    from lagrax.systems import pendulum
    assert len(jax.devices()) == 4, jax.devices()
    L = pendulum.lagrangian()
    a = jnp.linspace(0.05, 3.0, 50)
    one = lagrax.sweep_periods(L, a, method="quarter", lanes=8,
                               devices=jax.devices()[:1])
    four = lagrax.sweep_periods(L, a, method="quarter", lanes=8)
    assert four.num_devices == 4 and one.num_devices == 1
    np.testing.assert_array_equal(np.asarray(four.status), 0)
    np.testing.assert_allclose(four.periods, one.periods, rtol=1e-15, atol=0)
    np.testing.assert_allclose(four.periods, pendulum.period(a), rtol=1e-12)
    # The default method runs its passes per device (two rounds, the second only for
    # the lanes the bound cannot vouch for, compacted within each device): the same
    # periods, statuses and steps as one device, lane by lane.
    b = jnp.concatenate([a, jnp.array([jnp.nan])])  # 51 lanes: 4 devices pad one
    one = lagrax.sweep_periods(L, b, lanes=8, rtol=1e-15, atol=1e-15,
                               devices=jax.devices()[:1])
    four = lagrax.sweep_periods(L, b, lanes=8, rtol=1e-15, atol=1e-15)
    for k in ("periods", "status", "num_steps"):
        np.testing.assert_array_equal(np.asarray(getattr(four, k)),
                                      np.asarray(getattr(one, k)), err_msg=k)
    assert int(one.status[-1]) != 0 and int(one.status[0]) == 0
    np.testing.assert_allclose(four.error_estimate, one.error_estimate, rtol=1e-12)
    # Gradients through the sharded sweep: the one-device values.
    f = lambda devs: jax.grad(lambda q: jnp.sum(lagrax.sweep_periods(
        L, q, method="quarter", lanes=8, devices=devs).periods))(a[:6])
    np.testing.assert_allclose(f(jax.devices()), f(jax.devices()[:1]), rtol=1e-13)
    print("OK", float(jnp.max(jnp.abs(four.periods / one.periods - 1))))
    """
)


# Every lane on one device against two: the default method's two passes per device
# (the second compacted within each device), with 7 lanes so that one pads, and a
# failing lane; the four-device case with gradients is the slow version.
SMALL = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    import lagrax
    from lagrax.systems import pendulum
    assert len(jax.devices()) == 2, jax.devices()
    L = pendulum.lagrangian()
    b = jnp.array([0.05, 0.7, 1.4, jnp.nan, 2.1, 2.8, 3.0])
    # rtol 1e-15: the bound cannot vouch for every lane, so the second pass runs.
    tol = dict(rtol=1e-15, atol=1e-15)
    one = lagrax.sweep_periods(L, b, lanes=2, devices=jax.devices()[:1], **tol)
    two = lagrax.sweep_periods(L, b, lanes=2, **tol)
    assert two.num_devices == 2 and one.num_devices == 1
    for k in ("periods", "status", "num_steps"):
        np.testing.assert_array_equal(np.asarray(getattr(two, k)),
                                      np.asarray(getattr(one, k)), err_msg=k)
    ok = np.arange(7) != 3
    assert int(one.status[3]) != 0 and np.all(np.asarray(one.status)[ok] == 0)
    np.testing.assert_allclose(np.asarray(two.periods)[ok],
                               pendulum.period(b[ok]), rtol=1e-12)
    np.testing.assert_allclose(two.error_estimate, one.error_estimate, rtol=1e-12)
    print("OK")
    """
)


def _run(script, devices):
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}"
    ).strip()
    env["JAX_PLATFORMS"] = "cpu"
    proc = subprocess.run(
        [sys.executable, "-c", script],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "OK" in proc.stdout


def test_sharded_over_two_cpu_devices_matches_one_device():
    _run(SMALL, 2)


@pytest.mark.slow  # several configurations, and reverse mode through the sweep
def test_sharded_over_four_cpu_devices_matches_one_device():
    _run(SCRIPT, 4)
