"""Benchmarks of the diagnosis against a known truth or labels (imports :mod:`valve_emulator.diagnosis`, never
the other way round).

:mod:`.cases` and :mod:`.proof` (concealed simulated recordings with a known truth, ``valve-emulator prove``),
:mod:`.labelled` (labelled plant windows, the assessment and the literature detectors run side by side),
:mod:`.scorecard` (calls, confusion matrices, balanced accuracy) and :mod:`.evaluation` (the tables of
``valve-emulator evaluate``).
"""
