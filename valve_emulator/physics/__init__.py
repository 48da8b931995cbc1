"""Layer 1, physics: pure models stepped as arrays (no I/O, no clock, no pymodbus).

- :mod:`~valve_emulator.physics.stiction` -- the (S, J) stiction state machines
- :mod:`~valve_emulator.physics.actuator` -- the actuator's first-order lag before the valve's friction
- :mod:`~valve_emulator.physics.signal_chain` -- mA <-> % table, saturation, flow characteristic
- :mod:`~valve_emulator.physics.plant` -- transfer functions with dead time, exact zero-order hold
- :mod:`~valve_emulator.physics.controller` -- PI(D) position form with anti-windup and bumpless transfer
- :mod:`~valve_emulator.physics.disturbance` -- seeded load disturbances and measurement noise
- :mod:`~valve_emulator.physics.describing_function` -- N(A) of the stiction model
"""
