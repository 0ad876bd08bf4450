"""Steppers: one step of an integrator over many lanes (`base.py`), the explicit
Runge–Kutta step from a diffrax tableau, the Taylor step, the step-size controller."""
