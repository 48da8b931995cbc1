"""Many recordings at once, above the diagnosis of one (imports :mod:`valve_emulator.diagnosis`, never the other
way round).

- :mod:`.pool`: :func:`~.pool.run_ordered`, work items in this process or in worker processes with
  single-threaded compiled kernels, results in the items' order, a callback as each one finishes;
- :mod:`.sweep`: the plant-wide sweep of ``valve-emulator diagnose FOLDER`` (one machine or a Dask cluster)
  and its summary table (CSV, JSON).
"""
