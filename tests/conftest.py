"""Suite-wide settings.  ``make test`` runs the suite on two pytest-xdist workers (the CI machine
has 2 cores); each worker then uses one torch thread, so two workers do not fight over the cores."""

import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    # before uuomocap is imported: commands that would use every core (``uuomocap solve``) then
    # keep one thread here too, in-process and in the subprocesses the tests start
    os.environ["OMP_NUM_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)
