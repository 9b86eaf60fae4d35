"""uuomocap: motion capture from unstructured, unlabeled optical markers plus one video.

Import layout (the repository folders are mapped into this one package):
``uuomocap.solver_core`` (math), ``uuomocap.protocol`` (wire and file formats),
``uuomocap.nodes`` (processes), ``uuomocap.launch`` (graph files),
``uuomocap.cli`` and ``uuomocap.commands`` (the ``uuomocap`` command line).
"""

__version__ = "0.1.0"
