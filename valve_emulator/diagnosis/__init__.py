"""Diagnosis (layer 3): where a simulation and a recording differ, which physics the model leaves out.

``diagnose(recording, nominal)`` replays the nominal model on the recorded OP, locates the residual, and
searches a library of candidate physics (``stiction``, ``deadband``, ``dead_time``, ``characteristic``,
``actuator_lag``, ``saturation``, ``quantization``, ``disturbance``, and ``tuning`` judged on the loop; one
module each under :mod:`~valve_emulator.diagnosis.candidates`) by Hammerstein identification: a global grid over each candidate's parameters, vectorised over candidates, the linear part
re-fitted by output error around every one, the dead time searched with them, ranked by BIC and by the
free-run fit on a held-out part, added while significant. It returns a frozen
:class:`~valve_emulator.diagnosis.result.Diagnosis` (JSON, verdict, Markdown report; figure in
:mod:`~valve_emulator.diagnosis.plot`).

Modules, bottom up: ``data`` (checks; burn-in, fit and held-out parts), ``linear`` and
``linear_kernels`` (batched output-error fits), ``nominal`` (the starting model), ``chain`` and
``candidates`` (the physics, one module each; ``candidates.valve_start`` for a valve's unknown initial
state), ``models`` (result records), ``scoring`` (grids through the chain), ``evaluate`` (one candidate:
coarse, scan, refine), ``search`` (the rounds and the significance rule), ``locate``, ``uncertainty``,
``result`` (JSON, verdict, report), ``pipeline`` (the whole thing), ``plot``, ``cases`` and ``proof``
(concealed recordings with a known truth, ``valve-emulator prove``).

Plant data without a model (issue 7): ``output`` (candidates after the plant: backfitting and joint least
squares), ``crossval`` (two-fold blocked validation), ``resample`` (jittered recordings onto a grid),
``adequacy`` (when the data cannot tell), ``assessment`` (stiction / no stiction / cannot tell, with the
reason: ``assess(recording)``), ``plot_loop``, and for ``valve-emulator evaluate`` on a labelled set
``labelled`` (index, one window), ``scorecard`` (calls, confusion, balanced accuracy) and ``evaluation``.
"""

from valve_emulator.diagnosis.assessment import Assessment, assess
from valve_emulator.diagnosis.candidates import Candidate, ChainContext, get, register, registry
from valve_emulator.diagnosis.pipeline import RULE, RULE_TWOFOLD, diagnose
from valve_emulator.diagnosis.result import Diagnosis, Finding
from valve_emulator.diagnosis.search import DELTA_BIC, DELTA_FIT

__all__ = ["Assessment", "Candidate", "ChainContext", "DELTA_BIC", "DELTA_FIT", "Diagnosis", "Finding", "RULE",
           "RULE_TWOFOLD", "assess", "diagnose", "get", "register", "registry"]
