"""Shared pytest set-up.

Property tests run derandomized: the same examples on every run, so a red CI always means a
change broke something rather than a new random draw. `HYPOTHESIS_PROFILE=explore` searches
afresh (more examples, random seed) when hunting for edge cases locally.
"""

import os

from hypothesis import settings

settings.register_profile("default", derandomize=True, print_blob=True)
settings.register_profile("explore", max_examples=2000, derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))
