"""Modbus TCP clients for the emulator -- or any Modbus device (layer 5, beside the command line).

Each is a ``valve-emulator`` sub-command and ``python -m valve_emulator.clients.NAME``, with the same flags
(``add_arguments``), ``run(args)`` and ``main(argv=None) -> int``:

- :mod:`valve_emulator.clients.pi_controller` -- ``valve-emulator plc``: a soft PLC, PI(D) at a fixed scan time,
  any register addresses
- :mod:`valve_emulator.clients.recorder` -- ``valve-emulator record``: polls a device and writes the standard
  recording CSV, a flushed line per row
- :mod:`valve_emulator.clients.monitor` -- ``valve-emulator monitor``: the instructor's live terminal view:
  values, valve state, scrolling trend
- :mod:`valve_emulator.clients.scenario` -- ``valve-emulator scenario``: plays an operator-training scenario
  on an emulator it starts, or on a running one through its registers (the front end of
  :mod:`valve_emulator.scenario.player`)

Shared parts: :mod:`valve_emulator.clients._modbus` (register specs, grouped reads, the connection),
:mod:`valve_emulator.clients._channels` (what a recorder/monitor reads), :mod:`valve_emulator.clients._schedule`
(when to poll), :mod:`valve_emulator.clients._run` (Ctrl-C as a clean stop).
"""
