"""admc: adversarial Monte Carlo denoising (Xu et al. 2019) as a dataset-and-training pipeline.

The subpackages live in top-level folders (see pyproject's package-dir): `admc.pipeline`,
`admc.model`, `admc.stores`, `admc.cli`. Imports flow cli -> pipeline -> model -> stores.
"""

import os

# libgomp, the OpenMP runtime of torch and of flip-evaluator, spins 300,000 times after each parallel
# region before its threads sleep: milliseconds here, in which the next engine's threads (OpenVINO's,
# OIDN's) find both cores taken, and Table 1 timed that spin. 10,000 leaves torch's training step at its
# speed (0 halves it) and Table 1's times at those of a quiet process (docs/engines.md). The runtime reads
# it when it loads, so it is set before anything imports torch; a value in the environment wins.
os.environ.setdefault("GOMP_SPINCOUNT", "10000")

__version__ = "0.1.0"
