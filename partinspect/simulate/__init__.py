"""Synthetic stereo images of a CAD part, with exact ground truth.

- `rig`: the default calibrated stereo rig (``default_rig``, ``fixation_point``).
- `pose`: where the part sits (``default_pose``, ``parse_pose``).
- `render`: ray-cast, area-integrated, blurred, noisy 8-bit images.
- `truth`: nominal and as-rendered geometry and visibility of every feature.
- `folder`: ``render_to_folder``, what ``inspect render`` runs.

Nothing heavy (embreex, cadquery, trimesh) is imported until a render runs.
"""
