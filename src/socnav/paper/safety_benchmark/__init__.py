"""The safety-layer benchmark (experiment kind ``safety_benchmark``): every collision trigger calibrated at each
false-activation budget on calibration episodes, then played on held-out worlds (`benchmark`).

Importing this package registers the kind: its planner (`plan`), its units' executors and report section
(`socnav.paper.train_eval`, `units`).
"""

from socnav.paper import train_eval  # noqa: F401  (registers the train executor)
from socnav.paper.safety_benchmark import plan, units  # noqa: F401  (register the planner, executor and section)
