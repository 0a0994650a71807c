"""The allocator setting that keeps a worker's sampler off fresh mappings (:mod:`tembayes.common.heap`)."""

import os
import subprocess
import sys
import textwrap

import pytest

# a likelihood call's largest temporary: the (walkers, m x channels x windows) product, ~1 MB
_CHURN = textwrap.dedent(
    """
    import resource, sys
    import numpy as np
    if sys.argv[1] == "set":
        from tembayes.common.heap import keep_short_lived_blocks_on_the_heap
        assert keep_short_lived_blocks_on_the_heap()
    z, G = np.ones((27, 65)), np.ones((65, 4680))
    T = z @ G
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(500):
        T = z @ G
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    """
)


def _faults(mode):
    # the environment Dask's nanny gives its workers
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    out = subprocess.run([sys.executable, "-c", _CHURN, mode], env=env, capture_output=True, text=True, check=True)
    return int(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_worker_with_a_fixed_trim_threshold_reuses_its_heap_once_told_to():
    # 500 fresh 1 MB mappings fault in ~250 pages each; reused heap memory faults almost never
    untold, told = _faults("leave"), _faults("set")
    assert untold > 50_000
    assert told < untold / 20
