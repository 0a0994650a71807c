"""The paper's deterministic step method (``tembayes identify``): the baseline.

:func:`identify_batch` / :func:`identify_module` run it; :func:`to_json`
makes ``identify.json``; :mod:`tembayes.plots.identify` draws the figures.
"""

from tembayes.identify.pipeline import ModuleIdentification, batch_average, identify_batch, identify_module, to_json

__all__ = ["ModuleIdentification", "batch_average", "identify_batch", "identify_module", "to_json"]
