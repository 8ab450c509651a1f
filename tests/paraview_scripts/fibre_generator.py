"""pvpython: the Fibre Generator from the plugin's menu on a scene's muscles.vtm, bones.vtm and
attachments.csv (ParaView's own readers), feeding the Fibre Resampler, as a GUI user builds it.
Then the one-click pipeline on the scene (its attachments.csv read by the Fibre Resampler).
Arguments: SCENE COUNT POINTS. Prints RESULT with each block's fibre points, its fibre_grid,
bones, the resampler's particle count and the bones the pipeline's resampler hands on."""
import json
import os
import sys

from paraview import simple, servermanager

from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.plugin.pipeline import build_pipeline, load_plugin

scene, count, points = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
load_plugin()
path = lambda name: os.path.join(scene, name)  # noqa: E731
muscles = simple.XMLMultiBlockDataReader(FileName=[path("muscles.vtm")])
bones = simple.XMLMultiBlockDataReader(FileName=[path("bones.vtm")])
attachments = simple.CSVReader(FileName=[path("attachments.csv")], DetectNumericColumns=0)
generator = simple.FibreGenerator(Muscles=muscles, Bones=bones, Attachments=attachments)
generator.FibreCount, generator.PointsPerFibre = count, points
resampler = simple.FibreResampler(Fibres=generator, Bones=bones)
resampler.UpdatePipeline()
fibres = servermanager.Fetch(generator)
particles = servermanager.Fetch(resampler)
built = build_pipeline(scene, show=False)
built["Fibre Resampler"].UpdatePipeline()
handed_on = {name: [V.field(block, A.ORIGIN_BONE), V.field(block, A.INSERTION_BONE)]
             for name, block in V.blocks(servermanager.Fetch(built["Fibre Resampler"]))}
print("RESULT " + json.dumps({
    "pipeline_reads_attachments": "attachments" in built,
    "handed_on": handed_on,
    "blocks": {name: {"points": V.points_of(block).tolist(),
                      "grid": V.cell_array(block, A.FIBRE_GRID).tolist(),
                      "bones": [V.field(block, A.ORIGIN_BONE), V.field(block, A.INSERTION_BONE)]}
               for name, block in V.blocks(fibres)},
    "particles": sum(b.GetNumberOfPoints() for _, b in V.blocks(particles)),
}))
