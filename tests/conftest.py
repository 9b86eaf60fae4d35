"""Suite-wide settings.  ``make test`` runs the suite on two pytest-xdist workers (the CI machine
has 2 cores); each worker then uses one torch thread, so two workers do not fight over the cores."""

import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    import torch

    torch.set_num_threads(1)
