"""difareli.cli: the console entry points.

Importing this package chooses how torch's idle OpenMP threads wait before any command imports torch
(``difareli.utils.processes.openmp_for_machine``): passively (``OMP_WAIT_POLICY=PASSIVE``) where other work is running
when the command starts, since busy-waiting threads beside another job made one relight take 1.75 s to 50 s; libgomp's
own spin-then-sleep on a quiet machine, where passive waiting made a 64-px relight 2.1x and ``difareli-train`` 1.22x
slower. An explicit setting in the environment wins (docs/scaling_out.md, "Two jobs on one machine").
"""

from difareli.utils.processes import openmp_for_machine

openmp_for_machine()
