"""pvpython: read a scene folder with ParaView's own readers and with muscle_mss in ParaView's
Python; print what was read as ``RESULT <json>``. Argument: the scene folder."""
import json
import os
import sys

import numba
import numpy
import scipy
from paraview import simple
from paraview import servermanager

import muscle_mss.core
from muscle_mss.filters.scene_io import check_scene

folder = sys.argv[1]
muscles = simple.XMLMultiBlockDataReader(FileName=[os.path.join(folder, "muscles.vtm")])
muscles.UpdatePipeline()
motion = simple.CSVReader(FileName=[os.path.join(folder, "motion.csv")])
motion.UpdatePipeline()
mb = servermanager.Fetch(muscles)
table = motion.GetClientSideObject().GetOutputDataObject(0)
scene, problems = check_scene(folder)
print("RESULT " + json.dumps({
    "numba": numba.__version__, "numpy": numpy.__version__, "scipy": scipy.__version__,
    "core_file": muscle_mss.core.__file__,
    "muscle_blocks": [mb.GetMetaData(i).Get(mb.NAME()) for i in range(mb.GetNumberOfBlocks())],
    "muscle_points": muscles.GetDataInformation().GetNumberOfPoints(),
    "motion_rows": table.GetNumberOfRows(),
    "motion_columns": [table.GetColumnName(i) for i in range(table.GetNumberOfColumns())],
    "problems": problems,
    "time_points": len(scene.motion.times) if scene else None,
}))
