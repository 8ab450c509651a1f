"""Quasi-static method: the static equilibrium of the muscles' mass-spring model with contacts.

Where the paper's relaxation (:mod:`muscle_mss.core.relaxation`) stops after a fixed number of
explicit iterations, this minimises the model's energy (springs, volume pressure, connective
tissue, contacts as a penalty on overlapping pairs; g mm^2 / s^2) over the free particles by
L-BFGS, its initial inverse Hessian the spring matrix factorised once per topology, then runs the
paper's final collision passes. Tendon particles stay posed. The energy, the choices and their
measurements: docs/solver-notes.md, "How the quasi-static method works".

The package: :mod:`.preconditioner` (the constant part of the Hessian), :mod:`.energy` (the
energy and its gradient, contacts included), :mod:`.lbfgs` (the quasi-Newton direction and the
stopping estimate) and :mod:`.driver` (the minimisation and the final collision passes).
"""
from .driver import QuasiStaticResult, solve
from .energy import ContactEnergy
from .lbfgs import RATE_WINDOW, LBFGSHistory, distance_to_go
from .preconditioner import Preconditioner, model_springs, preconditioner

__all__ = ["ContactEnergy", "LBFGSHistory", "Preconditioner", "QuasiStaticResult",
           "RATE_WINDOW", "distance_to_go", "model_springs", "preconditioner", "solve"]
