"""pvpython: the six filters built by hand, one proxy at a time as a GUI user adds them (readers
of their own; the Spring Builder's optional Bones and the pose's optional Surfaces left
unconnected), beside the one-click builder's pipeline, both updated at one time. Issue 14: they
must give the same numbers.
Arguments: SCENE TIME ITERATIONS. Prints RESULT with, per output compared, the largest
difference between the two pipelines, and the radii each solver saw."""
import json
import os
import sys

import numpy as np
from paraview import simple

from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.plugin.pipeline import build_pipeline, load_plugin

scene, t, iterations = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
built = build_pipeline(scene, show=False, settings={"Iterations": iterations})

load_plugin()
path = lambda name: os.path.join(scene, name)  # noqa: E731
muscles = simple.XMLMultiBlockDataReader(FileName=[path("muscles.vtm")])
fibres = simple.XMLMultiBlockDataReader(FileName=[path("fibres.vtm")])
bones = simple.XMLMultiBlockDataReader(FileName=[path("bones.vtm")])
motion = simple.CSVReader(FileName=[path("motion.csv")])
resampler = simple.FibreResampler(Fibres=fibres)
springs = simple.SpringBuilder(Particles=resampler, Surfaces=muscles)
pose = simple.RigidPoseTransform(Model=springs, Bones=bones, Motion=motion)
solver = simple.MSSCollisionSolver(PosedModel=simple.OutputPort(pose, 0),
                                   PosedBones=simple.OutputPort(pose, 1))
solver.Iterations = iterations
deformer = simple.MVCSurfaceDeformer(SolvedModel=simple.OutputPort(solver, 0),
                                     RestSurfaces=muscles, RestModel=springs, RestBones=bones,
                                     PosedBones=simple.OutputPort(pose, 1))
probe = simple.VolumeErrorProbe(DeformedSurfaces=simple.OutputPort(deformer, 0),
                                RestSurfaces=muscles)
hand = {"Spring Builder": springs, "MSS Collision Solver": solver, "Volume-Error Probe": probe}


def output(proxy, port=0):
    proxy.UpdatePipeline(t)
    return proxy.GetClientSideObject().GetOutputDataObject(port)


def largest_difference(a, b):
    """The largest |difference| of the points and of every point array, over all blocks."""
    worst = 0.0
    for (name_a, block_a), (name_b, block_b) in zip(V.blocks(a), V.blocks(b)):
        assert name_a == name_b, (name_a, name_b)
        worst = max(worst, float(np.abs(V.points_of(block_a) - V.points_of(block_b)).max()))
        arrays_b = V.point_arrays(block_b)
        for key, values in V.point_arrays(block_a).items():
            worst = max(worst, float(np.abs(np.asarray(values, float)
                                            - np.asarray(arrays_b[key], float)).max()))
    return worst


def radii(proxy, port=0):
    return np.concatenate([V.point_array(b, A.RADIUS) for _, b in V.blocks(output(proxy, port))])


solved = [output(p["MSS Collision Solver"]) for p in (built, hand)]
surfaces = [output(p["Volume-Error Probe"]) for p in (built, hand)]
tables = [V.table_columns(output(p["Volume-Error Probe"], 1)) for p in (built, hand)]
moved = max(float(np.abs(V.point_array(b, A.DISPLACEMENT)).max()) for _, b in V.blocks(solved[1]))
print("RESULT " + json.dumps({
    "solved": largest_difference(*solved),
    "surfaces": largest_difference(*surfaces),
    "volume_error": float(np.abs(np.asarray(tables[0][A.VOLUME_ERROR_PCT])
                                 - np.asarray(tables[1][A.VOLUME_ERROR_PCT])).max()),
    "blocks": len(V.blocks(solved[1])),
    "largest_move": moved,
    "builder_model_radii_sum": float(radii(built["Spring Builder"]).sum()),
    "hand_model_radii_sum": float(radii(springs).sum()),
    "hand_posed_radii_sum": float(radii(pose).sum()),
}))
