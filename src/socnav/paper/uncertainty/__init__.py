"""Tables 2 and 3 of the paper (experiment kind ``uncertainty``): the perturbation study (the uncertainty estimated
at every step of perturbed episodes) and the safety layer (calibrated, played, ablated, traded off), with Figs. 5-6.

Importing this package registers the kind: its planner (`plan`), its units' executors (`socnav.paper.train_eval`,
`units`) and its report page (`report`, which lists where each table lives).
"""

from socnav.paper import train_eval  # noqa: F401  (registers the train executor)
from socnav.paper.uncertainty import plan, report, units  # noqa: F401  (register the planner, executors and page)
