import os

import jax
import pytest


# The library's disk cache of executables (`lagrax._executables`) off, unless a test
# turns it on: tests compile what they check, and write nothing outside their
# temporary folders.
os.environ["LAGRAX_CACHE_DIR"] = ""

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# Keep the suite honest on a 2-core CI machine: hypothesis examples are few but real.
from hypothesis import settings  # noqa: E402


settings.register_profile("ci", max_examples=25, deadline=None, derandomize=True)
settings.register_profile("dev", max_examples=50, deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")


@pytest.fixture
def key():
    return jax.random.key(5678)
