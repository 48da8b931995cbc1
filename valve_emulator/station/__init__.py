"""The instructor station: a browser HMI for trainees and an instructor page, in the device's process.

- :mod:`~valve_emulator.station.core` -- the station's model over a running device (state, run/freeze,
  speed, snapshots, malfunctions, operator actions, alarms);
- :mod:`~valve_emulator.station.evaluation` -- IAE, time outside limits, response times, the action log;
- :mod:`~valve_emulator.station.scenario_run` -- a scenario played by the station: timed events with ramps,
  triggers, hints, scoring rules;
- :mod:`~valve_emulator.station.report` -- the end-of-session report (HTML with trend PNGs);
- :mod:`~valve_emulator.station.app` -- the aiohttp adapter: HTTP API, server-sent events, the pages in
  ``static/`` (plain HTML, CSS and JavaScript drawing on canvas; no build step, nothing fetched).

``valve-emulator serve --web PORT`` starts it next to the Modbus server; ``docs/station.md`` is the manual.
"""

from valve_emulator.station.core import Station, StationError

__all__ = ["Station", "StationError"]
