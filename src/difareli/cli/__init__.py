"""difareli.cli: the console entry points.

Importing this package sets passive OpenMP waiting (``OMP_WAIT_POLICY=PASSIVE`` unless the environment says
otherwise) before any command imports torch: on a shared few-core CPU, busy-waiting threads made one relight take
1.75 s to 50 s (docs/scaling_out.md, "Two jobs on one machine").
"""

from difareli.utils.processes import passive_openmp

passive_openmp()
