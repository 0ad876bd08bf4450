"""Steppers: one step of an integrator over many lanes (`base.py`), the explicit
Runge–Kutta step from a diffrax tableau, the step-size controller. The Taylor step
lives with the rest of the Taylor code, in `lagrax._taylor`."""
