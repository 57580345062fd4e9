"""agents"""

import os
import sys

# One BLAS thread in every shapefleet process, set before numpy loads OpenBLAS: the grid basis's
# eigendecomposition (agents/kernel.py) then has the same bits on hosts of one CPU kind whatever their core count,
# so robots, `simulate` and `launch` agree bit for bit across machines; and the small matrices here
# gain nothing from threads (measured under load: one eigh 246 ms with a thread per core vs 6.6 ms
# with one; the default run's CPU -24 %). A value the user exported wins (setdefault) and is
# inherited by every robot process, so a fleet stays consistent either way.
_USER_SET_BLAS = "OPENBLAS_NUM_THREADS" in os.environ
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if "numpy" in sys.modules and not _USER_SET_BLAS:
    # A script that imported numpy first has already started OpenBLAS with a thread per core, which the
    # variable no longer changes: its in-process fleet would then not be simulate's bits (held-out 4's
    # pliers outline even changed outcome, benchmarks/results/autogrid.md). Limit the running pool instead.
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
