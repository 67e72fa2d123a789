"""admc: adversarial Monte Carlo denoising (Xu et al. 2019) as a dataset-and-training pipeline.

The subpackages live in top-level folders (see pyproject's package-dir): `admc.pipeline`,
`admc.model`, `admc.stores`, `admc.cli`. Imports flow cli -> pipeline -> model -> stores.
"""
__version__ = "0.1.0"
