"""uuomocap: motion capture from unstructured, unlabeled optical markers plus one video.

Import layout (the repository folders are mapped into this one package):
``uuomocap.solver_core`` (math), ``uuomocap.protocol`` (wire and file formats),
``uuomocap.nodes`` (processes), ``uuomocap.launch`` (graph files),
``uuomocap.cli`` and ``uuomocap.commands`` (the ``uuomocap`` command line).
"""

__version__ = "0.1.0"

import os as _os

# Whether the user chose the thread count: a command that runs alone on the machine (``uuomocap
# solve``) then keeps it, and otherwise uses every usable core (commands.solo_thread_count).
THREADS_FROM_ENVIRONMENT = "OMP_NUM_THREADS" in _os.environ

# One intra-op thread per process unless the user says otherwise.  The solver's tensors are small
# (tens of markers, a few hundred vertices per op), and a graph runs several processes on the
# same cores: torch's default of one thread per core then spins against the other nodes and
# slows a solve several-fold (measured: 190 CPU-s with the default vs 30 CPU-s with one thread
# for the same 75-frame solve on the loaded 2-core CI machine).  Must run before torch loads.
_os.environ.setdefault("OMP_NUM_THREADS", "1")
