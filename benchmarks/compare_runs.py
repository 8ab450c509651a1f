"""Compare the outputs of two runs bitwise: the check for a change meant to leave results as
they were (a refactor, a speed-up, a new option at its neutral value).

Each argument is a folder of run folders (what ``muscle-mss run SCENE OUT`` writes into OUT), or
one run folder; run folders are paired by name. For each pair it compares ``summary.csv`` and
every convergence table without their timing columns (any column whose name contains
"second"), and every numeric array of every series file (points, point, cell and field data)
byte for byte, and prints one line per run: the number of arrays and BITWISE SAME, or what
differs and by how much, and the columns and arrays only AFTER has (a new output). Exit status 1
when anything both have differs or AFTER lacks something.

    python benchmarks/compare_runs.py BEFORE AFTER

Make the runs from the same scene folders with each version of the code, e.g. for each of
the demo scenes (``muscle-mss demo-scene scenes/thigh``, ``... scenes/arm --region arm``), both
methods and a few times: ``muscle-mss run scenes/thigh before/thigh-paper-0.5 --time 0.5
--method paper --compressor none``, then the same into ``after/``.
"""
from __future__ import annotations

import csv
import glob
import os
import sys

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkIOXML import vtkXMLMultiBlockDataReader


def csv_columns(path) -> dict:
    """``{name: values}`` of a CSV file's columns without its timing columns."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return {name: [row[i] for row in rows[1:]] for i, name in enumerate(rows[0])
            if "second" not in name}


def series_arrays(vtm) -> dict:
    """Every numeric array of a multiblock series file: ``{(block, kind, name): array}``."""
    reader = vtkXMLMultiBlockDataReader()
    reader.SetFileName(vtm)
    reader.Update()
    data = reader.GetOutput()
    found = {}
    it = data.NewIterator()
    it.InitTraversal()
    while not it.IsDoneWithTraversal():
        block = it.GetCurrentDataObject()
        meta = it.GetCurrentMetaData()
        name = meta.Get(data.NAME()) if meta is not None else str(it.GetCurrentFlatIndex())
        if block.GetNumberOfPoints():
            found[(name, "points", "")] = vtk_to_numpy(block.GetPoints().GetData())
        for kind, arrays in (("point", block.GetPointData()), ("cell", block.GetCellData()),
                             ("field", block.GetFieldData())):
            for k in range(arrays.GetNumberOfArrays()):
                array = arrays.GetAbstractArray(k)
                if array.IsNumeric() and "second" not in (array.GetName() or ""):
                    found[(name, kind, array.GetName())] = vtk_to_numpy(array)
        it.GoToNextItem()
    return found


def compare_run(before, after) -> tuple:
    """``(arrays compared, problems, added)`` of two run folders: ``added`` names the columns
    and arrays only AFTER has (a new output is not a difference in what both compute)."""
    problems, added = [], set()
    tables = ["summary.csv"] + [os.path.relpath(path, before) for path in
                                sorted(glob.glob(os.path.join(before, "convergence", "*.csv")))]
    for table in tables:
        old, new = (csv_columns(os.path.join(folder, table)) for folder in (before, after))
        added |= set(new) - set(old)
        if set(old) - set(new) or any(old[c] != new[c] for c in old):
            problems.append(table)
    count = 0
    for vtm in sorted(glob.glob(os.path.join(before, "series", "*.vtm"))):
        name = os.path.basename(vtm)
        old, new = series_arrays(vtm), series_arrays(os.path.join(after, "series", name))
        added |= {key[2] or key[1] for key in set(new) - set(old)}
        if set(old) - set(new):
            problems.append(f"{name}: arrays {sorted(set(old) - set(new))[:3]} missing")
        for key in sorted(set(old) & set(new)):
            count += 1
            a, b = old[key], new[key]
            if a.shape != b.shape or a.tobytes() != b.tobytes():
                gap = (np.abs(a.astype(float) - b.astype(float)).max()
                       if a.shape == b.shape else "shape")
                problems.append(f"{name} {key}: max difference {gap}")
    return count, problems, added


def run_folders(root) -> dict:
    """``{name: folder}`` of the run folders in ``root`` (``root`` itself when it is one)."""
    if os.path.isfile(os.path.join(root, "summary.csv")):
        return {os.path.basename(os.path.normpath(root)): root}
    return {name: os.path.join(root, name) for name in sorted(os.listdir(root))
            if os.path.isfile(os.path.join(root, name, "summary.csv"))}


def main(argv=None) -> int:
    before_root, after_root = (argv if argv is not None else sys.argv[1:])[:2]
    before, after = run_folders(before_root), run_folders(after_root)
    if len(before) == 1 and len(after) == 1:
        after = {name: folder for name, folder in zip(before, after.values())}
    differ = False
    for name, folder in before.items():
        if name not in after:
            print(f"{name}: missing in {after_root}")
            differ = True
            continue
        count, problems, added = compare_run(folder, after[name])
        differ |= bool(problems)
        print(f"{name}: {count} arrays, " + ("BITWISE SAME" if not problems else
                                              "DIFFERS: " + "; ".join(problems[:6]))
              + (f" (new in {after_root}: {', '.join(sorted(added))})" if added else ""))
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
