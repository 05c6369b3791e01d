"""Shared pytest set-up.

Property tests run derandomized: the same examples on every run, so a red CI always means a
change broke something rather than a new random draw. `HYPOTHESIS_PROFILE=explore` searches
afresh (more examples, random seed) when hunting for edge cases locally.
"""

import os

from hypothesis import settings

# Mesa's EGL (the reference-site renderer) and triton (pulled in by torchvision) both bring an LLVM; loading
# torchvision after an EGL context exists segfaults the process, the other order is fine. Test modules
# render and train in the same worker, so torchvision is loaded first, here.
try:
    import torchvision.ops  # noqa: F401
except ImportError:  # pragma: no cover - torch is a declared dependency
    pass

settings.register_profile("default", derandomize=True, print_blob=True)
settings.register_profile("explore", max_examples=2000, derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))
