"""Visualisation of the social-navigation scene: RGB frames, animations and a live viewer.
Headless-safe (Agg canvas, pyplot only imported by `HumanViewer` when it is used)."""

from socnav.viz.animation import ALLOWED_EXTENSIONS, HumanViewer, check_animation_path, save_animation
from socnav.viz.render import SceneFrame, SceneRenderer

__all__ = ["ALLOWED_EXTENSIONS", "HumanViewer", "SceneFrame", "SceneRenderer", "check_animation_path", "save_animation"]
