"""The assess step for plant data without a model: *is this valve sticky?*

:mod:`.adequacy` says whether the data can tell at all; :mod:`.decision` runs the explain step without a
model and turns its findings into one :class:`~valve_emulator.diagnosis.answers.Answer` (stiction, no
stiction and why, cannot tell and why) by one rule for every loop, held in :mod:`.result`.
"""
