import os
import subprocess
import sys
import textwrap


SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    import lagrax
    from lagrax.systems import pendulum
    assert len(jax.devices()) == 4, jax.devices()
    L = pendulum.lagrangian()
    a = jnp.linspace(0.05, 3.0, 50)
    one = lagrax.sweep_periods(L, a, method="quarter", chunk_size=8,
                               devices=jax.devices()[:1])
    four = lagrax.sweep_periods(L, a, method="quarter", chunk_size=8)
    assert four.num_devices == 4 and one.num_devices == 1
    np.testing.assert_array_equal(np.asarray(four.status), 0)
    np.testing.assert_allclose(four.periods, one.periods, rtol=1e-15, atol=0)
    np.testing.assert_allclose(four.periods, pendulum.pendulum_period(a), rtol=1e-12)
    # The default method runs its passes per device (two rounds, the second only for
    # the lanes the bound cannot vouch for, compacted within each device): the same
    # periods, statuses and steps as one device, lane by lane.
    b = jnp.concatenate([a, jnp.array([jnp.nan])])  # 51 lanes: 4 devices pad one
    one = lagrax.sweep_periods(L, b, chunk_size=8, rtol=1e-15, atol=1e-15,
                               devices=jax.devices()[:1])
    four = lagrax.sweep_periods(L, b, chunk_size=8, rtol=1e-15, atol=1e-15)
    for k in ("periods", "status", "num_steps"):
        np.testing.assert_array_equal(np.asarray(getattr(four, k)),
                                      np.asarray(getattr(one, k)), err_msg=k)
    assert int(one.status[-1]) != 0 and int(one.status[0]) == 0
    np.testing.assert_allclose(four.error_estimate, one.error_estimate, rtol=1e-12)
    # Gradients through the sharded sweep: the one-device values.
    f = lambda devs: jax.grad(lambda q: jnp.sum(lagrax.sweep_periods(
        L, q, method="quarter", chunk_size=8, devices=devs).periods))(a[:6])
    np.testing.assert_allclose(f(jax.devices()), f(jax.devices()[:1]), rtol=1e-13)
    print("OK", float(jnp.max(jnp.abs(four.periods / one.periods - 1))))
    """
)


def test_sharded_over_four_cpu_devices_matches_one_device():
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
    ).strip()
    env["JAX_PLATFORMS"] = "cpu"
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "OK" in proc.stdout
