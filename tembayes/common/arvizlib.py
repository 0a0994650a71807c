"""ArviZ, as tembayes imports it: ``from tembayes.common.arvizlib import az``.

arviz 0.2x issues a ``FutureWarning`` on import, once a day per user cache,
announcing its coming 1.x refactor whenever the refactored packages
(arviz-base, arviz-stats, arviz-plots) are not installed.  It concerns no
call tembayes makes, so no change of API removes it, and the packages that
would: arviz-plots 0.8 (the last for Python 3.11) breaks ``import arviz`` on
matplotlib 3.11, and the 1.x line needs Python 3.12.  This one notice is
therefore not shown (matched by its text); every other arviz warning is.
Importing arviz anywhere in tembayes through this module keeps the notice
out of every process, the Dask workers' included.
"""

import warnings

#: The start of the text of arviz's import-time notice.
REFACTOR_NOTICE = r"\s*ArviZ is undergoing a major refactor"

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=REFACTOR_NOTICE, category=FutureWarning)
    import arviz as az

__all__ = ["az"]
