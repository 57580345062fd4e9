"""agents"""

import os

# One BLAS thread in every shapefleet process, set before numpy loads OpenBLAS: the grid basis's
# eigendecomposition (agents/kernel.py) then has the same bits on hosts of one CPU kind whatever their core count,
# so robots, `simulate` and `launch` agree bit for bit across machines; and the small matrices here
# gain nothing from threads (measured under load: one eigh 246 ms with a thread per core vs 6.6 ms
# with one; the default run's CPU -24 %). A value the user exported wins (setdefault) and is
# inherited by every robot process, so a fleet stays consistent either way.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
