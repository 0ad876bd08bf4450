import numpy as np, jax.numpy as jnp, lagrax, mpmath as mp
import diffrax as dfx
from scipy.optimize import brentq
from lagrax.systems import asymmetric_well
WELL = asymmetric_well.lagrangian()
mp.mp.dps = 40
def exact(q0):
    q0 = mp.mpf(float(q0))
    E = q0**2/2 + q0**3/3
    roots = sorted(mp.re(r) for r in mp.polyroots([-mp.mpf(1)/3, -mp.mpf(1)/2, 0, E], maxsteps=400, extraprec=400))
    r2, a, b = roots
    x = lambda p: a + (b - a) * (1 - mp.cos(p)) / 2
    return 2 * mp.quad(lambda p: 1 / mp.sqrt(mp.mpf(2) / 3 * (x(p) - r2)), [0, mp.pi])
def test_probe():
    x = np.linspace(0, 1, 4)
    V = lambda x: 0.5 * x**2 + x**3 / 3
    left = brentq(lambda x: V(x) - 0.99 / 6, -1, 0)
    right = brentq(lambda x: V(x) - 0.99 / 6, 0, 2)
    q0 = jnp.concatenate([jnp.linspace(left, -1e-3, 64), jnp.linspace(1e-3, right, 64)])
    idx = [0, 1, 2, 60, 124, 125, 126, 127]
    ex = np.array([float(exact(q0[i])) for i in idx])
    ref = np.asarray(lagrax.quadrature_period(WELL, q0, throw=False).periods)[idx]
    print("oracle vs mp", ["%.1e" % v for v in np.abs(ref/ex-1)])
    for s in [dfx.Dopri8(), lagrax.Taylor()]:
        for rt in [1e-13, 1e-14]:
            r = lagrax.sweep_periods(WELL, q0, solver=s, rtol=rt, atol=rt)
            T = np.asarray(r.periods)[idx]; est = np.asarray(r.error_estimate)[idx]
            true = np.abs(T/ex-1)
            print(type(s).__name__, rt, [("%.1e"%t, "%.1e"%e) for t, e in zip(true, est)])
