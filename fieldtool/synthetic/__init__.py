"""Synthetic seeded rivers with a known discharge (for `fieldtool demo` and accuracy tests).

>>> from fieldtool.synthetic import presets, render_scene
>>> truth = render_scene(presets.get("oblique"), "demo_out/scene")   # doctest: +SKIP
>>> truth.discharge_m3s, truth.project_path                          # doctest: +SKIP
"""

from fieldtool.synthetic import presets
from fieldtool.synthetic.camera import Camera
from fieldtool.synthetic.scene import River, SceneSpec, SceneTruth, gcp_distances, gcp_world, render_scene

__all__ = ["Camera", "River", "SceneSpec", "SceneTruth", "gcp_distances", "gcp_world", "presets", "render_scene"]
