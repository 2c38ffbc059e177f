"""Tissue Twin core: session I/O, registration, FEM replay, learning and diagnosis.

Layers (each imports only from layers to its left; checked by import-linter):
``core.io`` -> ``core.registration`` -> ``core.simulation`` -> ``core.lab`` ->
``core.learning`` | ``core.diagnosis``. ``core`` never imports ``app``.
"""

__version__ = "0.1.0"
