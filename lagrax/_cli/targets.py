r"""What `lagrax sweep` sweeps: built-in systems and your own Lagrangians.

A built-in is a module of `lagrax.systems`: its `lagrangian(**params)`, its exact
`period` and `small_amplitude_period` where it has them, and its `SWEEP` (a
`lagrax.systems.SweepSpec`: the amplitude's symbol, default range, method, the
coordinate it is integrated in). Your own is `module:attr` or `path/to/file.py:attr`
(the convention of uvicorn and gunicorn), naming `L(q, qdot, t)` or a factory that
returns one; its amplitude is the release point $q_0$.
"""

import importlib
import importlib.util
import inspect
import math
import os
import re
import sys
from dataclasses import dataclass, field

from .parser import DEFAULT_TARGETS, first_line, UsageError


@dataclass
class Target:
    name: str  # as given on the command line
    L: object  # kept for the whole run: sweep_periods caches its compiled code on it
    amplitude_label: str = "q₀"
    description: str = ""  # what the system is, for the chart (default: the name)
    to_q0: object = None  # amplitude -> release point (None: the identity)
    exact: object = None  # amplitude -> exact period, or None
    T0: float | None = None
    default_range: tuple | None = None
    bounds: tuple | None = None  # (lo, hi) with lo < amplitude <= hi, or None
    method: str = "matched"
    extra: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------
# Built-in systems


def builtin_names():
    import pkgutil

    from .. import systems

    return sorted(
        m.name for m in pkgutil.iter_modules(systems.__path__) if m.name[0] != "_"
    )


def builtin_module(name):
    return importlib.import_module(f"lagrax.systems.{name}")


def default_targets():
    """The built-ins whose `SWEEP` marks them for the default sweep."""
    return [
        name
        for name in builtin_names()
        if getattr(getattr(builtin_module(name), "SWEEP", None), "default", False)
    ]


def keywords_of(fn):
    """{name: default or inspect.Parameter.empty} of the keywords `fn` accepts, and
    whether it takes **kwargs."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return {}, True
    kws = {}
    var = False
    for p in sig.parameters.values():
        if p.kind is p.VAR_KEYWORD:
            var = True
        elif p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD):
            kws[p.name] = p.default
    return kws, var


def _call_with(fn, params, *args):
    """`fn(*args, **params)` with only the parameters `fn` accepts (for references)."""
    kws, var = keywords_of(fn)
    if not var:
        params = {k: v for k, v in params.items() if k in kws}
    return fn(*args, **params)


def _call_factory(factory, params, what):
    kws, var = keywords_of(factory)
    unknown = [k for k in params if k not in kws and not var]
    if unknown:
        have = ", ".join(kws) or "none"
        raise UsageError(
            f"{what} has no parameter {unknown[0]!r} (its parameters: {have})"
        )
    missing = [
        k for k, d in kws.items() if d is inspect.Parameter.empty and k not in params
    ]
    if missing:
        raise UsageError(
            f"{what} needs the parameter {missing[0]!r} (give it with --param "
            "NAME=VALUE; where it is not a number, write a module that builds the "
            "Lagrangian and sweep it as module:attr)"
        )
    try:
        return factory(**params)
    except Exception as e:  # noqa: BLE001 - the user's code
        args = ", ".join(f"{k}={v!r}" for k, v in params.items())
        raise UsageError(
            f"{what}: {getattr(factory, '__name__', 'factory')}({args}) raised "
            f"{first_line(e)}"
        ) from None


def _exact_period_fn(module, name):
    """`period` (the uniform layout) or `<name>_period` (the older one), or None."""
    for attr in ("period", f"{name}_period"):
        fn = getattr(module, attr, None)
        if callable(fn):
            return fn
    return None


def builtin(name, params):
    import jax.numpy as jnp
    import numpy as np

    from ..systems import SweepSpec

    module = builtin_module(name)
    if callable(getattr(module, "force", None)):
        raise UsageError(
            f"{name} is damped (its `force`), and a period sweep takes no force: "
            f"integrate it with lagrax.simulate(..., force=systems.{name}.force())"
        )
    spec = getattr(module, "SWEEP", None) or SweepSpec(name)
    L = _call_factory(spec.lagrangian or module.lagrangian, params, f"system {name!r}")
    amplitudes = spec.amplitudes
    if callable(amplitudes):
        try:
            amplitudes = _call_with(amplitudes, params)
        except Exception:  # noqa: BLE001 - parameters it cannot judge: no default
            amplitudes = None
    target = Target(
        name,
        L,
        spec.amplitude,
        description=spec.description,
        to_q0=spec.release_point,
        default_range=None if amplitudes is None else tuple(map(float, amplitudes)),
        bounds=spec.bounds,
        method=spec.method,
    )
    exact_fn = _exact_period_fn(module, name)
    if exact_fn is not None:
        target.exact = lambda amp, fn=exact_fn: (
            np.asarray(_call_with(fn, params, jnp.asarray(amp)), dtype=np.float64)
            * np.ones_like(amp)
        )
    small = getattr(module, "small_amplitude_period", None)
    try:
        if callable(small):
            target.T0 = float(_call_with(small, params))
        elif target.exact is not None:
            T0 = float(target.exact(np.zeros(1))[0])
            target.T0 = T0 if math.isfinite(T0) and T0 > 0 else None
    except Exception:  # noqa: BLE001 - a reference that cannot say: no T0
        target.T0 = None
    return target


# ------------------------------------------------------------------------------
# Your own Lagrangians


def _load_object(spec):
    """`module:attr` or `path/to/file.py:attr` -> (object, description)."""
    where, _, attr = spec.rpartition(":")
    if not where or not attr:
        raise UsageError(
            f"TARGET {spec!r}: expected module:attr or path/to/file.py:attr"
        )
    if where.endswith(".py") or os.sep in where or "/" in where:
        path = os.path.abspath(where)
        if not os.path.isfile(path):
            raise UsageError(f"TARGET {spec!r}: no such file {where!r}")
        name = "_lagrax_target_" + re.sub(r"\W", "_", path)
        loader = importlib.util.spec_from_file_location(name, path)
        if loader is None:
            raise UsageError(f"TARGET {spec!r}: cannot import {where!r} (not Python)")
        module = importlib.util.module_from_spec(loader)
        sys.modules[name] = module
        try:
            loader.loader.exec_module(module)
        except Exception as e:  # noqa: BLE001 - the user's code
            del sys.modules[name]
            raise UsageError(
                f"TARGET {spec!r}: importing {where!r} raised {first_line(e)}"
            ) from None
    else:
        # As uvicorn does: modules in the working directory are importable.
        if os.getcwd() not in sys.path and "" not in sys.path:
            sys.path.insert(0, os.getcwd())
        try:
            module = importlib.import_module(where)
        except ModuleNotFoundError as e:
            if e.name is not None and where.startswith(e.name):
                raise UsageError(
                    f"TARGET {spec!r}: no module named {e.name!r}"
                ) from None
            raise UsageError(
                f"TARGET {spec!r}: importing {where!r} raised {first_line(e)}"
            ) from None
        except Exception as e:  # noqa: BLE001 - the user's code
            raise UsageError(
                f"TARGET {spec!r}: importing {where!r} raised {first_line(e)}"
            ) from None
    obj = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise UsageError(f"TARGET {spec!r}: {where!r} has no attribute {part!r}")
        obj = getattr(obj, part)
    return obj


def _positional_arity(fn):
    """(required positional parameters, whether *args), or None if unknowable."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return None
    required = [
        p
        for p in sig.parameters.values()
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
        and p.default is p.empty
    ]
    star = any(p.kind is p.VAR_POSITIONAL for p in sig.parameters.values())
    return len(required), star


def _user(spec, params):
    obj = _load_object(spec)
    if not callable(obj):
        raise UsageError(
            f"TARGET {spec!r} is not callable (a {type(obj).__name__}): name a "
            "Lagrangian L(q, qdot, t) or a factory returning one"
        )
    arity = _positional_arity(obj)
    if arity is None or arity[0] == 3 or (arity[1] and arity[0] <= 3):
        if params:
            raise UsageError(
                f"TARGET {spec!r} is a Lagrangian L(q, qdot, t), not a factory: "
                "--param does not apply"
            )
        L = obj
    elif arity[0] == 0:
        L = _call_factory(obj, params, f"factory {spec!r}")
        if not callable(L):
            raise UsageError(
                f"factory {spec!r} returned a {type(L).__name__}, not a Lagrangian "
                "L(q, qdot, t)"
            )
        arity = _positional_arity(L)
        if arity is not None and not (arity[0] == 3 or (arity[1] and arity[0] <= 3)):
            raise UsageError(
                f"factory {spec!r} returned a function of {arity[0]} required "
                "argument(s), not a Lagrangian L(q, qdot, t)"
            )
    else:
        raise UsageError(
            f"TARGET {spec!r} takes {arity[0]} required argument(s): expected a "
            "Lagrangian L(q, qdot, t) or a factory f(**params) returning one"
        )
    return Target(spec, L, "q₀")


def check_one_dof(target):
    """`L(q, qdot, t)` must be a Lagrangian of one coordinate: the library's check,
    worded for the command line where it counts the coordinates."""
    import numpy as np

    from .._checks import check_one_dof as check, CoordinatesError

    what = f"TARGET {target.name!r}" if ":" in target.name else target.name
    try:
        check(target.L, np.float64)
    except CoordinatesError as e:
        n = e.coordinates
        raise UsageError(
            f"{what} has {n} coordinates (q of shape ({n},)); lagrax sweep needs a "
            "Lagrangian of one coordinate",
            coordinates=n,
        ) from None
    except (TypeError, ValueError) as e:
        raise UsageError(f"{what}: {e}") from None


# ------------------------------------------------------------------------------
# T₀ where no formula gives it


def _sign(x):
    return (x > 0) - (x < 0)


def small_oscillation_period(L, q0):
    r"""$T_0 = 2\pi/\omega$ of small oscillations about the bottom of the well that a
    release from rest at `q0` swings through, or None where there is none.

    The bottom is the first point where $\ddot q(q, \dot q = 0)$ changes sign, going
    the way it points at `q0` (steps doubling up to a sixteenth of the scale
    $\max(|q_0|, 1)$, then bisection); $\omega^2 = -\partial\ddot q/\partial q$
    there, which must be positive (a stable equilibrium).
    """
    import jax
    import jax.numpy as jnp

    import lagrax

    def qddot(q):
        return lagrax.accelerations(L, q[None], jnp.zeros((1,), q.dtype), 0.0)[0]

    f = jax.jit(qddot)
    at = lambda q: float(f(jnp.float64(q)))
    try:
        a, fa = float(q0), at(q0)
        scale = max(abs(a), 1.0)
        h = 1e-3 * scale
        b = a
        for _ in range(400 if fa != 0 else 0):
            b = a + _sign(fa) * h
            fb = at(b)
            if not math.isfinite(fb) or _sign(fb) != _sign(fa):
                break
            a, fa, h = b, fb, min(2 * h, scale / 16)
        else:
            if fa != 0:
                return None
        if fa != 0:
            if not math.isfinite(fb):
                return None
            for _ in range(200):  # bisection to adjacent floats
                m = 0.5 * (a + b)
                if m in (a, b):
                    break
                if _sign(at(m)) == _sign(fa):
                    a = m
                else:
                    b = m
        omega2 = -float(jax.grad(qddot)(jnp.float64(0.5 * (a + b))))
    except Exception:  # noqa: BLE001 - L not differentiable or singular there
        return None
    if not (math.isfinite(omega2) and omega2 > 0):
        return None
    return 2 * math.pi / math.sqrt(omega2)


# ------------------------------------------------------------------------------
# The targets of a command line


def _fmt(x):
    """An amplitude bound as the user reads it: π as π."""
    return "π" if x == math.pi else f"{x:g}"


def targets(args):
    import numpy as np

    builtins = set(builtin_names())
    names = []
    for name in args.targets:
        names.extend(default_targets() if name == DEFAULT_TARGETS else [name])
    if len(set(names)) != len(names):
        raise UsageError(f"a TARGET is given twice: {' '.join(args.targets)}")
    out = []
    for name in names:
        if ":" in name:
            target = _user(name, args.params)
        elif name in builtins:
            target = builtin(name, args.params)
        else:
            raise UsageError(
                f"unknown system {name!r}: a built-in ({', '.join(sorted(builtins))}; "
                "see `lagrax systems`) or your own as module:attr or file.py:attr"
            )
        check_one_dof(target)
        target.method = args.method or target.method
        if target.default_range is None and (args.amin is None or args.amax is None):
            raise UsageError(
                f"{name}: give the amplitudes with --min and --max (release points "
                f"{target.amplitude_label})"
            )
        lo = target.default_range[0] if args.amin is None else args.amin
        hi = target.default_range[1] if args.amax is None else args.amax
        if lo > hi:
            raise UsageError(
                f"--min must not exceed --max; got --min {lo} --max {hi} for {name}"
            )
        if target.bounds is not None:
            b0, b1 = target.bounds
            if not (b0 < lo <= hi <= b1):
                raise UsageError(
                    f"amplitudes {target.amplitude_label} of the {name} must satisfy "
                    f"{_fmt(b0)} < --min <= --max <= {_fmt(b1)}; got --min {lo} "
                    f"--max {hi}"
                )
        target.extra["range"] = (lo, hi)
        if target.T0 is None:
            q_lo = lo if target.to_q0 is None else target.to_q0(np.array([lo]))[0]
            target.T0 = small_oscillation_period(target.L, float(q_lo))
        reference = args.reference
        if reference == "auto":
            reference = "exact" if target.exact is not None else "none"
        if reference == "exact" and target.exact is None:
            raise UsageError(
                f"{name} has no exact period: use --reference quadrature (natural "
                "systems) or --reference none"
            )
        target.extra["reference"] = reference
        out.append(target)
    return out


def _default_text(value):
    if value is inspect.Parameter.empty:
        return "<required>"
    if callable(value):  # a function's name, not its repr with an address
        return getattr(value, "__name__", type(value).__name__)
    return repr(value)


def systems_lines():
    """`lagrax systems`: one line per built-in, its parameters and what it sweeps."""
    import numpy as np

    lines = []
    names = builtin_names()
    defaults = set(default_targets())
    width = max(len(n) for n in names)
    for name in names:
        module = builtin_module(name)
        factory = getattr(module, "lagrangian", None)
        if not callable(factory):
            continue
        kws, _ = keywords_of(factory)
        params = " ".join(f"{k}={_default_text(d)}" for k, d in kws.items())
        notes = []
        if callable(getattr(module, "force", None)):
            notes.append("damped (its force): not for lagrax sweep")
            lines.append(f"{name:<{width}}  {params}  [{'; '.join(notes)}]")
            continue
        try:
            target = builtin(name, {})
            check_one_dof(target)
        except UsageError as e:
            text = str(e)
            if e.coordinates is not None:
                notes.append(f"{e.coordinates} coordinates: not for lagrax sweep")
            elif "needs the parameter" in text:
                notes.append("needs a function argument: sweep it as module:attr")
            else:
                notes.append(f"not for lagrax sweep: {text}")
        else:
            notes.append(
                "exact period"
                if target.exact is not None
                else "no exact period (--reference quadrature)"
            )
            if target.default_range is not None:
                lo, hi = target.default_range
                notes.append(
                    f"amplitude {target.amplitude_label} {lo:g}..{np.round(hi, 6):g}"
                )
            else:
                notes.append("needs --min/--max")
            if name in defaults:
                notes.append("default")
        lines.append(f"{name:<{width}}  {params}  [{'; '.join(notes)}]")
    return lines
