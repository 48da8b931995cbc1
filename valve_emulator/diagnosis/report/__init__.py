"""What a diagnosis hands back: frozen result records, their JSON and Markdown, and the figures.

:mod:`.explanation` (findings, the explain step's record, the verdict sentence), :mod:`.assessment` (the
answer for a plant loop), :mod:`.diagnosis` (the public result of :func:`valve_emulator.diagnose`, with the
fitted model), :mod:`.plot` and :mod:`.plot_loop` (figures).
"""
