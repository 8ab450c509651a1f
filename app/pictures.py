"""PNG pictures of a scene for people (DESIGN §7): the demo's ``preview.png``.

pyvista is imported inside the functions only: ParaView's Python has no pyvista, and the filters
package must import there.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.motion import farthest_pose_index

from muscle_mss.filters import array_names as A

MUSCLE_COLOURS = (
    "#d62728", "#ff7f0e", "#bcbd22", "#2ca02c", "#17becf", "#1f77b4", "#9467bd",
    "#e377c2", "#8c564b", "#7f7f7f", "#aec7e8", "#ffbb78", "#98df8a",
)
"""One colour per muscle in block order (repeated beyond 13 muscles)."""
BONE_COLOUR = "#f5f2ea"
BLEND_FALLOFF = 20.0
"""Distance (mm) over which a muscle point's pose blends from its nearest bone to the next."""


def _pyvista_off_screen():
    """pyvista set to render off-screen. Without a display VTK's default window tries the X
    server first and prints "bad X server connection" before it falls back to EGL; there
    the EGL window is asked for directly (when libEGL is present and the user chose no
    window class)."""
    import ctypes.util
    import os

    import pyvista
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) \
            and ctypes.util.find_library("EGL"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    pyvista.OFF_SCREEN = True
    return pyvista


def _transform(matrix, points):
    return points @ matrix[:, :3].T + matrix[:, 3]


def pose_time(motion, time=None) -> float:
    """The time (s) shown as the moving pose: ``time`` itself, or, when None, the time point
    at which the bones are rotated farthest from the rest pose in total (mid-swing in the demo
    walking cycle, where the knee is flexed most)."""
    if time is not None:
        return float(time)
    return float(motion.times[farthest_pose_index(motion)])


def _matrices_at(motion, time):
    """Bone transforms (B, 3, 4) at ``time`` (s), linearly interpolated and clamped; good
    enough for a picture (the pose filter interpolates rotations properly)."""
    t = np.clip(time, motion.times[0], motion.times[-1])
    i = int(np.clip(np.searchsorted(motion.times, t) - 1, 0, max(len(motion.times) - 2, 0)))
    if len(motion.times) == 1:
        return motion.matrices[0]
    w = (t - motion.times[i]) / (motion.times[i + 1] - motion.times[i])
    return (1.0 - w) * motion.matrices[i] + w * motion.matrices[i + 1]


def posed_points(scene, points, matrices) -> np.ndarray:
    """Move muscle or fibre ``points`` (n, 3) mm by a blend of the bone ``matrices`` (B, 3, 4)
    weighted by closeness to each bone's rest surface (a picture's approximation of the pose
    filter's blending)."""
    names = list(scene.motion.bones)
    distances = np.column_stack([cKDTree(scene.bones[b].points).query(points)[0] for b in names])
    weights = np.exp(-(distances - distances.min(axis=1, keepdims=True)) / BLEND_FALLOFF)
    weights /= weights.sum(axis=1, keepdims=True)
    moved = np.stack([_transform(m, points) for m in matrices], axis=1)
    return np.einsum("nb,nbj->nj", weights, moved)


def scene_preview(scene, path, time=None, window_size=(1600, 1100)) -> str:
    """Write a PNG of ``scene`` to ``path``: the rest pose beside the pose at ``time`` (s;
    default :func:`pose_time`). Bones are white and posed by their matrices, muscles in
    distinct colours and their fibres in black are moved by a blend of the bone transforms.

    Returns the path written.
    """
    pyvista = _pyvista_off_screen()

    if scene.motion is None:
        raise MuscleMSSError("scene has no motion; the preview shows the rest and a moved pose")
    missing = [b for b in scene.motion.bones if b not in scene.bones]
    if missing:
        raise MuscleMSSError(f"motion names bones that the scene lacks: {', '.join(missing)}")
    shown = pose_time(scene.motion, time)
    plotter = pyvista.Plotter(off_screen=True, shape=(1, 2), window_size=list(window_size),
                              border=False)
    rest = np.stack([np.hstack([np.eye(3), np.zeros((3, 1))])] * len(scene.motion.bones))
    for column, (matrices, title) in enumerate(((rest, "rest pose"),
                                                (_matrices_at(scene.motion, shown),
                                                 f"t = {shown:.2f} s"))):
        plotter.subplot(0, column)
        plotter.set_background("#30343c")
        plotter.add_text(title, font_size=12, color="white")
        for b, name in enumerate(scene.motion.bones):
            bone = scene.bones[name]
            plotter.add_mesh(_surface_mesh(pyvista, _transform(matrices[b], bone.points),
                                           bone.triangles),
                             color=BONE_COLOUR, smooth_shading=True)
        for m, (name, muscle) in enumerate(scene.muscles.items()):
            colour = MUSCLE_COLOURS[m % len(MUSCLE_COLOURS)]
            plotter.add_mesh(_surface_mesh(pyvista, posed_points(scene, muscle.points, matrices),
                                           muscle.triangles),
                             color=colour, opacity=0.75, smooth_shading=True)
            fibres = scene.fibres.get(name)
            if fibres is not None and fibres.count:
                plotter.add_mesh(_polylines(pyvista, posed_points(scene, fibres.points, matrices),
                                            fibres.offsets), color="black", line_width=1)
        # Antero-lateral view: hip and knee flexion are seen nearly side on.
        plotter.view_vector((1.0, 0.8, 0.2), viewup=(0.0, 0.0, 1.0))
        plotter.reset_camera()
        plotter.camera.zoom(1.2)
    plotter.screenshot(str(path))
    plotter.close()
    return str(path)


def _surface_mesh(pyvista, points, triangles):
    faces = np.column_stack([np.full(len(triangles), 3), triangles]).reshape(-1)
    return pyvista.PolyData(np.asarray(points, dtype=np.float64), faces)


def _polylines(pyvista, points, offsets):
    sizes = np.diff(offsets)
    cells = np.concatenate([np.concatenate([[n], np.arange(o, o + n)])
                            for o, n in zip(offsets[:-1], sizes)])
    return pyvista.PolyData(np.asarray(points, dtype=np.float64), lines=cells)


def convergence_picture(convergence_csv, path, title="") -> str:
    """Plot a solver convergence table (``convergence/convergence_<k>.csv``): mean displacement
    per iteration of each muscle, log scale (the paper's figures 5 and 6), and the quasi-static
    solver's residual where the table has one. Returns ``path``."""
    import csv

    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import pyplot

    with open(convergence_csv, newline="") as f:
        rows = list(csv.DictReader(f))
    iterations = [int(r[A.ITERATION]) for r in rows]
    prefix = A.MEAN_DISPLACEMENT
    figure, axes = pyplot.subplots(figsize=(9, 5.5), dpi=120)
    for m, column in enumerate(c for c in rows[0] if c.startswith(prefix)):
        axes.plot(iterations, [max(float(r[column]), 1e-12) for r in rows],
                  color=MUSCLE_COLOURS[m % len(MUSCLE_COLOURS)], lw=1.2,
                  label=column[len(prefix):].replace("_", " "))
    if A.RESIDUAL in rows[0]:
        # the quasi-static solver's largest particle move of a step: what its tolerance bounds
        axes.plot(iterations, [max(float(r[A.RESIDUAL]), 1e-12) for r in rows], color="black",
                  lw=1.6, ls="--", label="residual (largest move)")
    axes.set_yscale("log")
    axes.set_xlabel(A.ITERATION)
    axes.set_ylabel("mean displacement per iteration (mm)")
    axes.set_title(title or "solver convergence")
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=7, ncol=2)
    figure.tight_layout()
    figure.savefig(path)
    pyplot.close(figure)
    return str(path)


def poses_picture(pipeline, index, path, window_size=(1800, 800), solved=None) -> str:
    """Write a PNG of three panels at time point ``index`` of a
    :class:`~muscle_mss.app.motion_run.Pipeline`: the rest pose, the rigid-only pose (the
    Rigid Pose Transform's surfaces) and the solved pose (the MVC Surface Deformer's surfaces,
    or ``solved``: the path of a run's surfaces ``.vtm`` of that time point, so that a run
    whose time points were solved elsewhere, in worker processes or not kept, does not solve
    it again), as the paper's figure 1. Returns ``path``."""
    from muscle_mss.filters import vtk_arrays as V
    from .motion_run import update_at

    t = pipeline.times[index]
    rest_bones = pipeline.bones.GetOutputDataObject(0)
    if solved is None:
        solved_surfaces = update_at(pipeline.deformer, 0, t)
    else:
        from vtkmodules.vtkIOXML import vtkXMLMultiBlockDataReader
        reader = vtkXMLMultiBlockDataReader()
        reader.SetFileName(str(solved))
        reader.Update()
        solved_surfaces = reader.GetOutput()
    panels = (("rest pose", pipeline.muscles.GetOutputDataObject(0), rest_bones),
              (f"rigid only, t = {t:.2f} s", update_at(pipeline.pose, 2, t),
               update_at(pipeline.pose, 1, t)),
              (f"solved, t = {t:.2f} s", solved_surfaces, update_at(pipeline.pose, 1, t)))
    pyvista = _pyvista_off_screen()
    plotter = pyvista.Plotter(off_screen=True, shape=(1, 3), window_size=list(window_size),
                              border=False)
    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    for column, (title, muscles, bones) in enumerate(panels):
        plotter.subplot(0, column)
        plotter.set_background("#30343c")
        plotter.add_text(title, font_size=11, color="white")
        meshes = [(pyvista.wrap(bone), BONE_COLOUR) for _, bone in V.blocks(bones, "bones")]
        meshes += [(pyvista.wrap(muscle), MUSCLE_COLOURS[m % len(MUSCLE_COLOURS)])
                   for m, (_, muscle) in enumerate(V.blocks(muscles, "muscles"))]
        for mesh, colour in meshes:
            plotter.add_mesh(mesh, color=colour, smooth_shading=True)
            if mesh.n_points:
                low = np.minimum(low, np.asarray(mesh.bounds[0::2]))
                high = np.maximum(high, np.asarray(mesh.bounds[1::2]))
    # one camera for the three panels, framing everything any of them shows: the posed limb
    # swings out of the rest pose's box (a forearm at 130 degrees, a shank at full knee flexion)
    for column in range(len(panels)):
        plotter.subplot(0, column)
        plotter.view_vector((1.0, 0.8, 0.2), viewup=(0.0, 0.0, 1.0))
        plotter.reset_camera(bounds=np.stack([low, high], axis=1).ravel().tolist())
        plotter.camera.zoom(1.25)
    plotter.link_views()
    plotter.screenshot(str(path))
    plotter.close()
    return str(path)
