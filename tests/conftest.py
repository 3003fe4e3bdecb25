"""Suite-wide settings. Property tests draw the same examples on every run and machine (a failure is then a
regression, never the luck of a seed); HYPOTHESIS_PROFILE=explore searches with fresh random seeds instead, which
is how new counterexamples are found (each one becomes an @example of its test)."""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("suite", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "suite"))
