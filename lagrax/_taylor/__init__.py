"""The Taylor integrator in one place: `Taylor` (`taylor.py`) and its diffrax solver
(`diffrax_solver.py`); the coefficient programs, unrolled (`program.py`,
`recurrences.py`, `solve.py`, `system.py`) and compact (`compact.py`); the lane
steppers of the period and trajectory loops on either (`stepper.py`,
`compact_stepper.py`)."""
