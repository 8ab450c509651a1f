"""Quasi-static method: the static equilibrium of the muscles' mass-spring model with contacts.

The paper's relaxation (:mod:`muscle_mss.core.relaxation`) stops after a fixed number of explicit
iterations, far from rest. This method minimises the model's energy over the free particles
(tendon particles stay at their posed positions); at the minimum every free particle's forces
balance. Masses, damping and drag play no part in a static equilibrium.

Energy (g mm^2 / s^2)::

    E(x) = sum_springs k (|x_b - x_a| - L0)^2 / 2                 (Hooke, as mss.spring_forces)
         + sum_muscles B V0 (V / V0 - 1)^2 / 2                    (volume pressure, BulkModulus B)
         + w / 2 sum_pairs max(0, r_i + r_j - |c_i - c_j|)^2      (contacts)

The contact term is a penalty on every overlapping pair of spheres of different muscles and of
a muscle sphere with a bone sphere (tendon spheres against bones are exempt, as in the paper),
or, given :class:`~muscle_mss.core.bone_distance.BoneSolids`, of a muscle particle with a bone
as a solid (``max(0, r_i + clearance - d(c_i))`` with ``d`` the bone's signed distance, looked
up with a continuous gradient (:mod:`muscle_mss.core.smooth_distance`; the trilinear lookup's
kinks at cell faces held particles pressed into a bone in place with forces left, and the
flexed poses never met the tolerance): a
particle is pushed out along the distance gradient from any depth, where a sphere past a bone's
shell of spheres is pulled on through it by the springs: on the full demo at the most flexed
pose the sphere-set solve was still drifting after thousands of iterations, its particles up to
85 mm apart between 250 and 4,000 iterations):
each sphere of an overlapping pair is pushed along the centre line by ``w`` times the overlap,
the whole push going to the free sphere when the other is fixed or a bone. Unlike the paper's
response (the deepest pair of each other object) the sum over all pairs is continuously
differentiable, so the minimisation converges where the paper's rule makes contacts chatter.
``w`` is :attr:`~muscle_mss.core.settings.QuasiStaticSettings.weight` times the largest sum of one particle's
spring stiffnesses (260 g/s^2 for a lattice-26 particle at the Spring Builder's defaults), times
the particle's muscle's resolution scale (19 / (N - 1) at N particles per fibre; a pair takes the
mean of its two, :func:`~.driver.contact_stiffness`), so that a finer lattice's contacts press
as hard per length of fibre. The
penalty leaves an overlap of (contact force) / w at the minimum; the final collision passes of
the paper method (:func:`muscle_mss.core.contacts.project`, against the solids when given)
remove it, after the free spheres are pushed out of the bone solids
(:func:`~muscle_mss.core.quasi_static.driver.push_out_of_solids`). Against the solids the penalty holds every free particle that
is not inside a bone at rest (``MSSModel.in_bone_at_rest``), with its sphere's radius or none
(:func:`muscle_mss.core.solid_contacts.solid_points`): an interior particle dragged into a bone is
pushed out as well.

Minimisation: L-BFGS (Liu, Bouaziz and Kavan 2017, "Quasi-Newton methods for real-time
simulation of hyperelastic materials") whose initial inverse Hessian is ``(A + K)^-1``: ``A = L``
the spring Laplacian weighted by stiffness, fixed particles' rows and columns removed,
factorised once per topology (one banded Cholesky factor per muscle, :class:`~.preconditioner.Preconditioner`),
and ``K`` each muscle's rank-one volume stiffness ``(B / V0) g g^T``, ``g = dV/dx`` at the
state of every :data:`~.driver.VOLUME_REFRESH`-th iteration (Sherman-Morrison; refreshing ``g``
every iteration doubles the triangular solves, and an initial inverse Hessian held for a few
iterations is as good a start for the history). A step of ``A^-1`` alone is the local/global step of Liu et
al. 2013; the history of the last :attr:`~muscle_mss.core.settings.QuasiStaticSettings.history` steps corrects it
towards Newton's. Contacts are left out of ``A``: a diagonal ``w`` on every sphere particle
pins the free surface (the walking pose of the full demo then did not converge in 500
iterations), refactorising ``A`` with each iteration's contacts cost 0.1 s per iteration at
N = 20, and Newton steps solved by conjugate gradients preconditioned with ``A`` needed 80
products each (74 s for the walking pose against 12.6 s). A backtracking line search
(Armijo) makes every iteration lower the energy, and a step moves no particle farther than the
largest muscle sphere radius (a longer step could jump over a contact); its first trial is at
most :data:`~.driver.STEP_GROWTH` times the last accepted fraction of the step (where muscles
touch, the full step overshoots). Contacts are found
from candidate lists (spheres of other objects within their radii plus a skin,
:func:`muscle_mss.core.spatial_hash.candidate_lists`) rebuilt whenever a sphere has moved half
the skin since: the energy is that of all overlapping pairs.

Termination by residual: the residual of an iteration is the largest particle move of its
quasi-Newton step (mm, before the line search), the L-BFGS estimate of the distance to the
minimum. The loop stops when it is below ``tolerance`` and so is the distance still to go
estimated from its decay (:func:`~.lbfgs.distance_to_go`), and the plain preconditioned step
``(A + K)^-1 grad E`` is below ``tolerance`` as well (it bounds the force: ``|f| <= |A + K| tolerance``);
then the final collision passes run. Where the energy can no longer see progress (the last
step lowered it by no more than its rounding), the plain step within the tolerance is enough
(the force is bounded; the distance still to go, estimated from steps that no longer lower the
energy, is noise), and :data:`~.driver.STALLED_STEPS` such steps in a row stop the loop
unconverged (``stopped_by`` "energy rounding"). Without this the demo thigh at 80 particles per
fibre (t = 0.2 s) ran to its cap: the energy stopped changing after about 300 iterations, the
plain step 0.0007 mm, while the L-BFGS steps jumped up to 20 mm.
The solve has converged when the loop stopped so and
the passes left no overlap above ``penetration_tolerance``. ``iterations`` caps the loop and
``time_budget`` (when set) bounds its wall-clock seconds. Warm start: ``start`` positions (e.g.
the solution of a neighbouring time point carried by the pose change) replace the posed
positions of the free particles; ``time_budget`` counts when the termination is ``time
budget``.

The package: :mod:`.preconditioner` (the constant part of the Hessian, factorised once per
topology), :mod:`.energy` (the energy and its gradient, contacts included), :mod:`.lbfgs` (the
quasi-Newton direction and the stopping estimate) and :mod:`.driver` (the minimisation and the
final collision passes).
"""
from .driver import QuasiStaticResult, solve
from .energy import ContactEnergy
from .lbfgs import RATE_WINDOW, LBFGSHistory, distance_to_go
from .preconditioner import Preconditioner, model_springs, preconditioner

__all__ = ["ContactEnergy", "LBFGSHistory", "Preconditioner", "QuasiStaticResult",
           "RATE_WINDOW", "distance_to_go", "model_springs", "preconditioner", "solve"]
