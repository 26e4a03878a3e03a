"""Visualisation of the social-navigation scene: RGB frames, animations and a live viewer; and a training run's
curve as a PNG (`plot_training_curve`, what `socnav plot` draws).
Headless-safe (Agg canvas, pyplot only imported by `HumanViewer` when it is used)."""

from socnav.viz.animation import ALLOWED_EXTENSIONS, HumanViewer, check_animation_path, save_animation
from socnav.viz.curves import TrainingCurveError, plot_training_curve
from socnav.viz.render import SceneFrame, SceneRenderer

__all__ = ["ALLOWED_EXTENSIONS", "HumanViewer", "SceneFrame", "SceneRenderer", "TrainingCurveError",
           "check_animation_path", "plot_training_curve", "save_animation"]
