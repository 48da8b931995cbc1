"""What a diagnosis hands back: the public result, its JSON and Markdown, and the figures.

:mod:`.diagnosis` (the public result of :func:`valve_emulator.diagnose`, with the fitted model), built
from the explain step's record (:mod:`valve_emulator.diagnosis.explain.result`: findings, verdict) and the
assess step's (:mod:`valve_emulator.diagnosis.assess.result`: the answer for a plant loop); :mod:`.plot`
and :mod:`.plot_loop` (figures).
"""
