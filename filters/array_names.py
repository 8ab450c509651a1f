"""Names of every VTK array that travels between the filters (DESIGN §5).

These names are the contract between stages and the format of saved data and state files:
use the constants, never the literals.
"""

# Point data of a muscle block (particles).
REST_POSITION = "rest_position"      # float64 x3, particle position in the rest pose, mm
FIBRE_ID = "fibre_id"                # int32, which fibre of the muscle
FIBRE_INDEX = "fibre_index"          # int32, place along the fibre, 0 = origin end
FIBRE_GRID = "fibre_grid"            # int32 x2, (row, col) of the fibre in the cross-section grid
FIBRE_MIDPOINT = "fibre_midpoint"    # float64 x3 cell data of the Fibre Resampler's polylines:
#                                      the fibre's middle vertex, mm (its placement check)
FIXED = "fixed"                      # uint8, 1 for the two end particles of each fibre
BOUNDARY = "boundary"                # uint8, 1 for particles in collisions and in the MVC cage
RADIUS = "radius"                    # float64, collision sphere radius, mm (0 if not boundary)
MASS = "mass"                        # float64, particle mass, g
BONE_WEIGHTS = "bone_weights"        # float64 x B, blend weight of each bone (pose filter)
VELOCITY = "velocity"                # float64 x3, mm/s (solver)
DISPLACEMENT = "displacement"        # float64 x3, solved minus posed position, mm (solver)
COLLIDED = "collided"                # uint8, collided in the last iteration (solver)
IN_BONE_AT_REST = "in_bone_at_rest"  # uint8, 1 inside a bone in the rest pose (pose filter): the
#                                      solver's solid bones keep the other free particles out

# Cell data of the spring cells (two-point lines) of a muscle block.
REST_LENGTH = "rest_length"          # float64, mm
STIFFNESS = "stiffness"              # float64, g/s^2 (force per mm of stretch; model units mm, s, g)
DAMPING = "damping"                  # float64, g/s (along the spring)

# Cell data of the deformed fibre polylines (MVC Surface Deformer).
FIBRE_LENGTH = "fibre_length"        # float64, mm
FIBRE_STRAIN = "fibre_strain"        # float64, length / rest length - 1
FIBRE_END_STRAIN = "fibre_end_to_end_strain"  # float64, chord / rest chord - 1 (the chord: the
#                                               distance from the fibre's first point to its last)
FIBRE_ARC_CHORD = "fibre_arc_chord"  # float64, length / chord: 1 straight, more when it bends
FIBRE_KEPT_SHAPE_STRAIN = "fibre_kept_shape_strain"  # float64, the FIBRE_STRAIN the fibre would
#   have if its muscle kept its rest shape and volume, stretched along its origin-insertion line
#   by its mean chord / rest chord (core.fibre_shortening.kept_shape_lengths): a reference for
#   FIBRE_STRAIN, by which curved fibres of a thickening muscle shorten less than its ends
FIBRE_BEND = "fibre_bend"            # float64, FIBRE_ARC_CHORD over the fibre's at rest: 1 as
#                                      curved as at rest, more where it folds or wraps a bone

# Point data of the deformed surfaces (MVC Surface Deformer with bones).
NEW_IN_BONE_DEPTH = "new_in_bone_depth"  # float64, mm a vertex outside a bone at rest was inside
#                                          it before the push out (0 elsewhere)

# Columns of the Volume-Error Probe's table (besides the field-data names below).
MUSCLE = "muscle"                    # string, the muscle (block) name; last row "mean"

# Field data.
MUSCLE_NAME = "muscle_name"          # string, the block name
# solved model blocks (MSS Collision Solver) and summary.csv: free (non-tendon) particles whose
# centre is inside a posed bone, all and those not inside a bone at rest, and the deepest, mm
FREE_IN_BONE = "free_particles_in_bone"
FREE_IN_BONE_DEPTH_MM = "free_particle_bone_depth_mm"
FREE_NEW_IN_BONE = "free_particles_new_in_bone"
FREE_NEW_IN_BONE_DEPTH_MM = "free_particle_new_in_bone_depth_mm"
FREE_IN_BONE_FIELDS = (FREE_IN_BONE, FREE_IN_BONE_DEPTH_MM, FREE_NEW_IN_BONE,
                       FREE_NEW_IN_BONE_DEPTH_MM)
ORIGIN_BONE = "origin_bone"          # string, bone of the fibres' first points (fibres.vtm,
                                     # optional; carried to the particles and the model)
INSERTION_BONE = "insertion_bone"    # string, bone of the fibres' last points (likewise)
BONE_NAMES = "bone_names"            # string x B, order of the bone_weights components
REST_VOLUME = "rest_volume"          # float64, mm^3 (Volume-Error Probe)
VOLUME = "volume"                    # float64, mm^3
VOLUME_ERROR_PCT = "volume_error_pct"  # float64, %
NEW_IN_BONE_VERTICES = "new_in_bone_vertices"  # float64, surface vertices inside a posed bone
#                                                they were outside at rest, before the push out
NEW_IN_BONE_DEPTH_MM = "new_in_bone_depth_mm"  # float64, mm, the deepest of them
NEW_IN_BONE_VERTICES_AFTER = "new_in_bone_vertices_after_push"  # the same after the push out
NEW_IN_BONE_DEPTH_AFTER_MM = "new_in_bone_depth_after_push_mm"  # (NaN: no bones connected)
IN_OTHER_MUSCLE_VERTICES = "in_other_muscle_vertices"  # float64, deformed surface vertices
#                                                         inside another muscle's surface
IN_OTHER_MUSCLE_DEPTH_MM = "in_other_muscle_depth_mm"  # float64, mm, the deepest of them
CAGE_DRIFT = "cage_drift"            # float64, mm per deformed vertex: its distance to its
#                                      cage now minus at rest (core.cage_drift)
CAGE_DRIFT_MM = "cage_drift_mm"      # float64, mm, field data: the largest of a surface
CAGE_DRIFT_VERTICES = "cage_drift_vertices"  # float64, field data: vertices drifting more than
#                                              core.cage_drift.CAGE_DRIFT_LIMIT
PROJECTION_PASSES = "projection_passes"  # float64, collision passes after the last iteration
REMAINING_PENETRATION = "remaining_penetration"  # float64, mm, deepest overlap they left
CONVERGED = "converged"              # float64 1/0, the solve reached its tolerance (solver)
METHOD = "method"                    # string, the solver method that produced the table
TISSUE_SHARE_PCT = "tissue_share_pct"  # float64, %, field data of each solved muscle block:
#                                        the connective tissue's force over its springs' force

# Columns of the MSS Collision Solver's convergence table (one row per iteration).
ITERATION = "iteration"              # int, 1 = the first iteration
MEAN_DISPLACEMENT = "mean_displacement_"  # prefix of one column per muscle: + the muscle name, mm
COLLIDING_PAIRS = "colliding_pairs"  # int, sphere pairs in contact
MAX_PENETRATION = "max_penetration"  # float64, mm, the deepest overlap
SECONDS = "seconds"                  # float64, s since the solve began (summary.csv: of the time
#                                      point)
RESIDUAL = "residual"                # column of the solver's table: mm, largest move of a step
# field data of the solver's table: seconds of the solve's parts (the paper's Table 1 columns):
# the mass-spring steps, muscle-muscle and muscle-bone collision detection with their response,
# and the final collision passes
PHASE_SECONDS = {"mss": "mss_seconds", "muscle_cd": "muscle_cd_seconds",
                 "bone_cd": "bone_cd_seconds", "projection": "projection_seconds"}

# Columns of summary.csv (besides MUSCLE, the probe's volumes and in-bone counts, the solver's
# FREE_IN_BONE_FIELDS, CONVERGED and SECONDS above).
TIME = "time"                        # float64, s
MEAN_FIBRE_STRAIN = "mean_fibre_strain"
MAX_FIBRE_STRAIN = "max_fibre_strain"
MEAN_END_TO_END_STRAIN = "mean_end_to_end_strain"  # mean FIBRE_END_STRAIN of the muscle
MAX_ARC_CHORD = "max_arc_chord"      # largest FIBRE_ARC_CHORD of the muscle
MEAN_KEPT_SHAPE_STRAIN = "mean_kept_shape_strain"  # mean FIBRE_KEPT_SHAPE_STRAIN of the muscle
MAX_FIBRE_BEND = "max_fibre_bend"    # largest FIBRE_BEND of the muscle
SPHERE_OVERLAP_MM = "sphere_overlap_mm"  # mm, deepest overlap of the muscle's spheres
ITERATIONS = "iterations"            # int, iterations of the time point's solve
