"""Table 1 of the paper (experiment kind ``table1``): every algorithm trained on every training scenario with every
seed and tested in every evaluation scenario; its report is Table 1 with intervals, the curves and the claims.

Importing this package registers the kind: its planner (`plan`), the training and evaluation units
(`socnav.paper.train_eval`) and its report page (`report`).
"""

from socnav.paper import train_eval  # noqa: F401  (registers the train and eval executors)
from socnav.paper.table1 import plan, report  # noqa: F401  (register the planner and the page)
