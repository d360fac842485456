"""Suite-wide setup: one BLAS thread, as `make test` and every dran-edge shell use.

`dran_edge.cli.commands.bench` sets OPENBLAS_NUM_THREADS=1 when it is imported, which in a bare
`pytest` run happens after numpy has loaded OpenBLAS with its default pool: the test process
then keeps several threads while the processes it starts later get one, and
tests/test_radio.py's bit-identity check between the in-process and the three-process fleet
fails on the last bits. Set here, before any test module imports numpy, both sides match.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
