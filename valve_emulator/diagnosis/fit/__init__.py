"""Fitting one model to one recording: *how well does this chain of physics replay the recorded PV?*

Bottom up: :mod:`.data` (checks; burn-in, fit and held-out parts), :mod:`.cost` (N ln SSE, BIC, the cost
relative to a surface's minimum), :mod:`.linear` and :mod:`.linear_kernels`
(the linear part: batched output-error fits, compiled), :mod:`.nominal` (the starting model: the user's loop
or one identified from the data), :mod:`.chain` (OP → actuator → valve → characteristic → limit → flow),
:mod:`.records` (a fitted model, a cost surface, an option), :mod:`.scorer` (parameter grids through the chain
and the linear fit, BIC), :mod:`.fitter` (one candidate into a model: coarse grid, scan, refinement),
:mod:`.backfit` (candidates after the plant), :mod:`.crossval` (held-out fit without a nominal model),
:mod:`.uncertainty` (intervals from cost surfaces), :mod:`.load_check` (BIC under a drifting-load noise
model) and :mod:`.predict` (the fitted loop, replayed on any OP).
"""
