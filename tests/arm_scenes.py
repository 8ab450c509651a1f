"""The elbow demo scene written for a test, with the time point of its most flexed pose."""
import numpy as np

from muscle_mss.core.demo import arm as demo_arm
from muscle_mss.filters.scene_io import write_scene


def written_arm_at_full_flexion(size, folder):
    """``(scene, index)``: the elbow demo of ``size`` ("full", "small") written to ``folder``,
    and the index of its time point at the most flexed pose (130 degrees)."""
    scene = demo_arm.demo_arm_scene(size)
    write_scene(scene, folder)
    return scene, int(np.argmax(demo_arm.flexion_angles(scene.motion.times)))
