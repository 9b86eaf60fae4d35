"""Suite-wide settings.  ``make test`` runs the suite on two pytest-xdist workers (the CI machine
has 2 cores); each worker then uses one torch thread, so two workers do not fight over the cores."""

import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    # before uuomocap is imported: commands that would use every core (``uuomocap solve``) then
    # keep one thread here too, in-process and in the subprocesses the tests start
    os.environ["OMP_NUM_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)


# The files whose tests take most of the suite's time (seconds on the 2-core CI machine, session
# 19: 422 / 257 / 168 / 216 / 53; everything else ~100 together).  ``make test`` keeps a file on one
# worker and hands out files in collection order, two at a time per worker
# (``--no-loadscope-reorder``); listing the long ones first, in this order, should let the two
# workers end close together (~600 s each by those numbers) rather than one starting the longest
# file last.  CI runs with it took 734 and 658 s (741 s before) on a machine whose speed varies
# by a third between runs.
LONG_FILES_FIRST = ("test_windowed.py", "test_solver.py", "test_metrics.py", "test_graph_solver.py", "test_graph.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(LONG_FILES_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file keeps its own order
