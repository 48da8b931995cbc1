"""Modbus clients: soft PLC, recorder, live monitor."""
