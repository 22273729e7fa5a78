"""Sample parts loaded once and their renders, for the simulator tests.

Renders are small (816 x 683, the default rig's field of view at a third
of its resolution) and cached for the session, so the simulator tests stay
well under a minute.
"""

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
SIZE = (816, 683)

# A generated plate (random_part seed 10: round vertical corners, a counterbore and a countersink) at
# the pose bench_robustness drew for it: one round corner's side starts as a wedge on its top arc in
# the left image, and the countersink's cone turns edge-on to the right camera.
ROUND_CORNER_SEED = 10
ROUND_CORNER_POSE = [[0.690242808209607, -0.6742160546446546, -0.2626738993016086, -14.441758440396816],
                     [-0.6760840159046844, -0.4715870645803641, -0.5661413639354309, 46.28237400495501],
                     [0.257827983650166, 0.5683646295995832, -0.781336277582846, 383.8719470409501],
                     [0.0, 0.0, 0.0, 1.0]]


def step_path(name):
    path = REPO / "examples" / name / "part.step"
    if not path.is_file():
        pytest.skip(f"sample part {path} not found")
    return path


class Part:
    """A sample part loaded once: shape, inventory, render mesh and scene."""

    def __init__(self, name):
        from partinspect.cad.features import inventory
        from partinspect.cad.mesh import tessellate
        from partinspect.cad.step import load_step
        from partinspect.cad.raycast import RENDER_ANGULAR_TOLERANCE, RENDER_TOLERANCE
        from partinspect.cad.raycast import build_scene

        self.name = name
        self.path = step_path(name)
        self.shape = load_step(self.path)
        self.inv = inventory(self.shape)
        self.mesh = tessellate(self.shape, RENDER_TOLERANCE, RENDER_ANGULAR_TOLERANCE, inventory=self.inv)
        self.scene = build_scene(self.mesh)
        self._renders = {}

    def rig(self, distortion=False, size=SIZE):
        from partinspect.simulate.rig import default_rig

        return default_rig(size, distortion=distortion)

    def pose(self, rig):
        from partinspect.poses import default_pose

        return default_pose(self.shape, rig)

    def render(self, distortion=False, noise=0.0, seed=0, size=SIZE):
        """(rig, pose, (left, right)) for the default pose; cached."""
        from partinspect.simulate.render import render_pair

        key = (distortion, noise, seed, size)
        if key not in self._renders:
            rig = self.rig(distortion, size)
            pose = self.pose(rig)
            images, _ = render_pair(self.scene, rig, pose, noise=noise, seed=seed)
            self._renders[key] = (rig, pose, images)
        return self._renders[key]


def flat_mask(image, margin=4):
    """Pixels at least ``margin`` px from any grey change of a noiseless image."""
    import cv2

    img = np.asarray(image, np.float32)
    edges = (np.abs(cv2.Sobel(img, cv2.CV_32F, 1, 0)) + np.abs(cv2.Sobel(img, cv2.CV_32F, 0, 1))) > 0
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    return cv2.dilate(edges.astype(np.uint8), kernel) == 0
