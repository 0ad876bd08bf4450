"""Ready-made Lagrangians, each with its exact references.

Each module holds one system: its Lagrangian as a factory taking physical parameters as
keywords and returning a plain `L(q, qdot, t)`, its hand-derived equation of motion, and
exact references (periods) where they exist.
"""

from . import cycloid as cycloid, pendulum as pendulum, rectilinear as rectilinear
from .pendulum import pendulum_period as pendulum_period
