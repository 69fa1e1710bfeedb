"""Old name of the densification, Gaussian-parameter and PLY modules, kept working: stdr/_moved.py."""
from .._moved import alias

alias(__name__, "stdr.densify, stdr.gaussians, stdr.knn and stdr.io",
      {"strategy": "stdr.densify.strategy", "prune": "stdr.densify.prune", "gaussians": "stdr.gaussians",
       "knn": "stdr.knn", "ply": "stdr.io.ply", "export": "stdr.io.export"})
