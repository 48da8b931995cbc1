"""The explain step: *what does my model leave out?*

:func:`~valve_emulator.diagnosis.explain.pipeline.explain` replays the nominal model, locates the residual
(:mod:`.locate`), searches the candidate library round after round under one significance rule
(:mod:`.search`) and writes up each accepted piece of physics as a finding (:mod:`.findings`), all held in
one frozen record (:mod:`.result`: findings, the verdict sentence, JSON and Markdown).
"""
