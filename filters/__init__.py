"""The six pipeline filters as plain VTK algorithms, the Fibre Generator that makes a scene's
fibres, and the scene reader (DESIGN §5, §6 "Fibre generation").

``from muscle_mss.filters import FibreResampler, SpringBuilder, RigidPoseTransform,
MSSCollisionSolver, MVCSurfaceDeformer, VolumeErrorProbe, read_scene``

Names are imported on first use, so importing one filter does not import them all. Importing a
filter starts nothing else: the kernels it calls compile at their first call when this Python
has not compiled them yet. The application's entry points (the ``muscle-mss`` command, the
batch, the ParaView proxies) compile them first and say so
(:func:`~muscle_mss.app.warm_up.ensure_compiled`).
"""
import importlib

EXPORTS = {
    "FibreResampler": "fibre_resampler",
    "SpringBuilder": "spring_builder",
    "RigidPoseTransform": "rigid_pose_transform",
    "MSSCollisionSolver": "collision_solver",
    "MVCSurfaceDeformer": "mvc_surface_deformer",
    "VolumeErrorProbe": "volume_error_probe",
    "FibreGenerator": "fibre_generator",
    "read_scene": "scene_io",
    "write_scene": "scene_io",
}
"""Public name -> module of this package defining it."""

FILTER_NAMES = ("FibreResampler", "SpringBuilder", "RigidPoseTransform",
                "MSSCollisionSolver", "MVCSurfaceDeformer", "VolumeErrorProbe")
"""The pipeline's filters in order (a solved frame depends on their properties)."""
PLUGIN_FILTERS = FILTER_NAMES + ("FibreGenerator",)
"""The filters the ParaView plugin exposes: the pipeline's, and the Fibre Generator, which
makes fibres for a scene that has only muscle surfaces."""

__all__ = list(EXPORTS) + ["MuscleMSSError"]


def __getattr__(name):
    if name == "MuscleMSSError":
        from muscle_mss.core.errors import MuscleMSSError
        return MuscleMSSError
    if name in EXPORTS:
        module = importlib.import_module(f".{EXPORTS[name]}", __name__)
        return getattr(module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
