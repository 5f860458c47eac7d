"""agvviz: visual replay and debugging of fiducial-marker robot localisation.

Conventions (frames, transforms, perturbations, Euler order, units) are written once in
:mod:`agvviz.conventions`; every module follows them.
"""

__version__ = "0.1.0"
