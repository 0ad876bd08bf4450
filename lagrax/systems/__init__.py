"""Ready-made Lagrangians, each with its exact references.

Each module holds one system: its Lagrangian as a factory taking physical parameters as
keywords and returning a plain `L(q, qdot, t)`, its hand-derived equation of motion, and
exact references (periods) where they exist.
"""

from . import (
    asymmetric_well as asymmetric_well,
    charged_particle as charged_particle,
    cycloid as cycloid,
    damped_pendulum as damped_pendulum,
    double_pendulum as double_pendulum,
    driven_pendulum as driven_pendulum,
    pendulum as pendulum,
    rectilinear as rectilinear,
    rotating_hoop as rotating_hoop,
    sphere as sphere,
    spherical_pendulum as spherical_pendulum,
)
from .pendulum import pendulum_period as pendulum_period
